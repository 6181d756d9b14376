"""`rvggt_forward`: the whole VGGT forward pass (aggregator + heads) as one pure function.

    out = jax.jit(rvggt_forward)(params, images, config)

`config` is a static pytree node, so plain `jax.jit` compiles once per
(input shape, config); `static_argnames="config"` works too. For long sequences, donate
the images (`jax.jit(rvggt_forward, donate_argnums=1)`, as `rvggt` runs it): XLA may then
reuse their buffer once they are read, instead of holding them to the end (float32
images of 1000 frames need it to fit a TPU v6e; `rvggt_jax.memory_report`).
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any, Iterator

import chex
import jax
import jax.numpy as jnp

from rvggt_jax.model.aggregator import aggregator_forward
from rvggt_jax.ops.ordering import zeros_after
from rvggt_jax.ops.precision import precision_scope
from rvggt_jax.config import VGGTConfig
from rvggt_jax.ops.shards import frame_layout
from rvggt_jax.model.heads.camera import camera_head
from rvggt_jax.model.patch_embed import unit_images
from rvggt_jax.model.heads.dpt import dense_heads
from rvggt_jax.model.heads.projections import head_projections
from rvggt_jax.model.heads.track import track_head
from rvggt_jax.model import remat
from rvggt_jax.model.layers import Params
from rvggt_jax.model.inputs import _is_float, check_inputs


def heads_in_float32(tree: Any) -> Any:
    """`tree` with every floating-point leaf narrower than float32 (bf16, f16) as float32."""
    return jax.tree.map(lambda x: x.astype(jnp.float32) if _is_float(x) and jnp.result_type(x).itemsize < 4
                        else x, tree)


def rvggt_forward(params: Params, images: jax.Array, config: VGGTConfig,
                  query_points: jax.Array | None = None) -> dict[str, Any]:
    """VGGT forward pass.

    images: [B, S, 3, H, W] or [S, 3, H, W], float in [0, 1] or uint8 in [0, 255] (the
      smaller program argument), H and W multiples of 14.
    query_points: optional [B, N, 2] or [N, 2] pixel (x, y) in frame 0 (needs the track head).

    Returns (B is added when the input had none), as upstream:
      pose_enc [B,S,9], pose_enc_list (list of [B,S,9], one per camera-head iteration),
      depth [B,S,H,W,1], depth_conf [B,S,H,W], world_points [B,S,H,W,3],
      world_points_conf [B,S,H,W];
      with query points: track [B,S,N,2], vis [B,S,N], conf [B,S,N];
      on request (config.with_outputs): saliency [B,S,h*w], patch_tokens [B*S,h*w,C],
      descriptors [B,S,C] (`frame_descriptors`),
      aggregated_XX [B,S,P,2C], images [B,S,3,H,W] (upstream always returns this copy of
      the input; here only with `with_outputs(images=True)`).
    """
    images, query_points = check_inputs(params, images, config, query_points)
    return forward_frames(params, images, config, query_points)


def forward_frames(params: Params, images: jax.Array, config: VGGTConfig,
                   query_points: jax.Array | None = None) -> dict[str, Any]:
    """`rvggt_forward` on checked inputs, over the frames of this device: images
    [B, S, 3, H, W] are this device's frames (inside `parallel/`'s `jax.shard_map`, which
    enters `ops.shards.split_frames`; elsewhere all frames) and so is every per-frame
    output. Every float32 matmul inside runs at `config.dot_precision`."""
    with config_scope(config):
        return _forward_frames(params, images, config, query_points)


@contextlib.contextmanager
def config_scope(config: VGGTConfig) -> Iterator[None]:
    """Every float32 matmul traced inside runs at `config.dot_precision`: what a forward
    and each Flax part (`model.modules`) run under. (The attention kernel is data:
    `config.attention` reaches the blocks through `layers.BlockConfig`.)"""
    with precision_scope(config.dot_precision):
        yield


def _head_projections(params: Params, config: VGGTConfig, grid, with_track: bool, enabled: dict,
                      per_group=None) -> dict:
    """The kept layers held as the DPT heads' first step (`projections.head_projections`): the
    layers only DPT heads read, where their projections are narrower than the tokens
    (VGGT-1B: layers 4 and 11, 512 and 1024 of 2048 channels for the depth and point
    heads). None ({}) in a training step with remat: there each split of the aggregator's
    scans costs residuals (a micro train step's temporaries grew a third: 5.2 -> 6.9 MB
    at 8 frames, more than the plain step's 6.8), and the heads' recomputed groups re-read
    the kept layers anyway; a layer's size matters at inference lengths."""
    if config.remat != "none":
        return {}
    readers = {name: (params[name], config.dpt_head.intermediate_layer_idx, config.dpt_head.pos_embed)
               for name, on in enabled.items() if on}
    if with_track:
        readers["track_head"] = (params["track_head"]["feature_extractor"], config.track_layer_idx, False)
    # (a returned layer is projected too, and also kept whole: the heads' values do not
    # depend on which layers are returned)
    last = config.depth - 1
    if config.low_memory:  # the camera head reads the last layer's camera token alone
        return head_projections(readers, grid, 2 * config.embed_dim, (), per_group, reassembled=True,
                                tokens={last: (0,)} if config.enable_camera else None)
    return head_projections(readers, grid, 2 * config.embed_dim, {last} if config.enable_camera else set(), per_group)


def frame_descriptors(patch_tokens: jax.Array, batch: int) -> jax.Array:
    """Place descriptors [B, S, C] of the DINOv2 patch tokens [B*S, h*w, C]: each frame's
    tokens mean-pooled (in float32) and scaled to unit length, so that a dot product is a
    cosine similarity. DINOv2's pooled features are what visual place recognition builds
    on (AnyLoc, SALAD); the long-sequence pipeline proposes loops from them."""
    d = patch_tokens.astype(jnp.float32).mean(axis=1)
    d = d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    return d.reshape(batch, -1, d.shape[-1])


def _forward_frames(params: Params, images: jax.Array, config: VGGTConfig, query_points: jax.Array | None
                    ) -> dict[str, Any]:
    b, s, _, hh, ww = images.shape
    with_track = query_points is not None
    # The heads compute in float32 whatever dtype their weights are stored in (a tree cast
    # whole to bf16, the usual JAX idiom, would otherwise change the camera head's scan
    # carry dtype); as `cast_params` lays them out, this is a no-op.
    params = {name: (sub if name == "aggregator" else heads_in_float32(sub)) for name, sub in params.items()}
    grid = config.token_grid((hh, ww))
    enabled = {"depth_head": config.enable_depth, "point_head": config.enable_point}
    # a training step re-reads each frame group's tokens and recomputes its feature maps (config.remat)
    per_group = functools.partial(remat.checkpoint, config=config, part="head")
    project = _head_projections(params, config, grid, with_track, enabled, per_group)
    keep = (set(config.needed_layers(with_track)) - set(project)) | set(config.return_layers)
    agg, patch_tokens, saliency = aggregator_forward(params["aggregator"], images, config, keep, project)

    out: dict[str, Any] = {}
    if config.enable_camera:
        # the camera trunk attends across frames: every device runs it on every frame's
        # camera token (B x S x 2C floats) and keeps its own frames
        layout = frame_layout(s)
        cam = layout.gather(agg[config.depth - 1].token(0)[:, :, None], 1)
        pose_enc_list = [layout.local_part(pe, 1) for pe in camera_head(params["camera_head"], cam, config.camera_head)]
        out["pose_enc"] = pose_enc_list[-1]
        out["pose_enc_list"] = pose_enc_list
    out.update(dense_heads({name: params[name] for name, on in enabled.items() if on}, agg, config.dpt_head, grid,
                           per_group, half_outputs=config.low_memory))
    if with_track:
        tracks, vis, conf = track_head(params["track_head"], agg, config.track_head_config, grid, query_points,
                                       remat=per_group)
        out["track"], out["vis"], out["conf"] = tracks[-1], vis, conf
    if config.return_images:
        # a copy of the input (an argument cannot be an output), made at the end (x 1 made
        # from the last head output, exact), not held through the whole forward
        last = jax.tree.leaves(out)
        unit = unit_images(images)
        out["images"] = unit * (1.0 + zeros_after((), jnp.float32, last[-1])) if last else unit
    if config.return_saliency:
        out["saliency"], out["patch_tokens"] = saliency, patch_tokens
    if config.return_descriptors:
        out["descriptors"] = frame_descriptors(patch_tokens, b)
    for i in config.return_layers:
        out[f"aggregated_{i:02d}"] = agg[i].array()

    if "depth" in out:
        chex.assert_shape(out["depth"], (b, s, hh, ww, 1))
    return out
