"""`rvggt_forward`: the whole VGGT forward pass (aggregator + heads) as one pure function.

    out = jax.jit(rvggt_forward)(params, images, config)

`config` is a static pytree node, so plain `jax.jit` compiles once per
(input shape, config); `static_argnames="config"` works too.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any, Iterator

import chex
import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.errors import InputError  # noqa: F401 (re-exported: rvggt_jax.InputError)
from rvggt_jax.model.aggregator import aggregator_forward
from rvggt_jax.ops.attention import kernel_scope
from rvggt_jax.ops.ordering import zeros_from
from rvggt_jax.ops.precision import precision_scope
from rvggt_jax.config import VGGTConfig
from rvggt_jax.ops.shards import FrameShards
from rvggt_jax.model.heads.camera import camera_head
from rvggt_jax.model.patch_embed import unit_images
from rvggt_jax.model.heads.dpt import dense_heads
from rvggt_jax.model.heads.projections import head_projections
from rvggt_jax.model.heads.track import track_head
from rvggt_jax.model.input_range import InputRangeWarning, warn_if_out_of_range  # noqa: F401 (re-exported)
from rvggt_jax.model import remat
from rvggt_jax.model.layers import Params
from rvggt_jax.weights.layout import expected_param_paths, flatten_params


def _is_float(x: Any) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.floating)


def check_images(images: Any, config: VGGTConfig) -> jax.Array:
    """Validate and batch images: [S, 3, H, W] or [B, S, 3, H, W], float in [0, 1] or
    uint8 in [0, 255] -> [B, S, 3, H, W] (float32, or uint8 kept as it is: the program
    scales it, `unit_images`). Only static facts (rank, shape, dtype) are errors, so
    this also works on tracers under jit; float values outside [0, 1] or NaN are an
    `InputRangeWarning` (`warn_if_out_of_range`: at once for concrete arrays, from inside
    the program under jit)."""
    if isinstance(images, (list, tuple)):
        images = _stack_frames(images)
    shape = tuple(np.shape(images))
    if len(shape) not in (4, 5):
        raise InputError(f"images must be [S,3,H,W] or [B,S,3,H,W]; got rank {len(shape)} shape {shape}")
    dtype = jnp.result_type(images)
    if not (_is_float(images) or dtype == jnp.uint8):
        raise InputError(f"images must be a float array in [0, 1] or a uint8 array in [0, 255]; got dtype {dtype}")
    # a float image is legal whatever its values: only a warning (concrete arrays now, under
    # jit from inside the program); uint8 is in range by its type
    warn_if_out_of_range(images)
    if len(shape) == 4:
        images = images[None]
        shape = (1,) + shape
    b, s, c, h, w = shape
    if c != 3:
        raise InputError(f"images must have 3 (RGB) channels in axis -3; got {c} (shape {shape})")
    ps = config.patch_size
    if h % ps or w % ps:
        raise InputError(f"image height and width must be multiples of the patch size {ps}; got {h} x {w}")
    if min(b, s, h, w) == 0:
        raise InputError(f"images has an empty axis: shape {shape}")
    # uint8 stays uint8 into the program: a quarter of float32's argument bytes (0.57 of
    # 2.27 GiB at 1000 frames of 392 x 518), scaled where the patch embed reads it
    return jnp.asarray(images, jnp.uint8 if dtype == jnp.uint8 else jnp.float32)


def _stack_frames(frames: list | tuple) -> jax.Array:
    """A list of S frames [3, H, W] (arrays, or tracers under jit) -> one array [S, 3, H, W];
    `InputError` when they are no frames or differ in shape."""
    shapes = [tuple(np.shape(f)) if hasattr(f, "shape") else None for f in frames]
    if not frames or None in shapes or len(set(shapes)) != 1:
        got = "an empty list" if not frames else f"a list of shapes {shapes[:4]}{' ...' if len(shapes) > 4 else ''}"
        raise InputError(f"images must be one array [S,3,H,W] or [B,S,3,H,W] (or a list of arrays [3,H,W] "
                         f"of one shape); got {got}")
    return jnp.stack(frames)


QUERY_HELP = "query_points are pixel (x, y) in frame 0 of the network input, shape [N, 2] or [B, N, 2]"


def as_query_points(query_points: Any) -> jax.Array:
    """Query points as users write them -> [N, 2] or [B, N, 2] float32.

    A query point is a pixel (x, y) in frame 0 of the network input (the preprocessed
    image, e.g. 518 x 392, not the original photo): x to the right, y down, continuous.
    Lists, tuples, NumPy and JAX arrays of ints or floats are accepted (inside `jax.jit`
    a list arrives as a list of scalars); anything else is an `InputError` saying what
    was given."""
    if query_points is None or isinstance(query_points, (str, bytes, dict, set)):
        raise InputError(f"{QUERY_HELP}; got a {type(query_points).__name__}")
    try:
        qp = jnp.asarray(query_points)
    except (TypeError, ValueError) as e:
        raise InputError(f"{QUERY_HELP}; cannot read a {type(query_points).__name__} as numbers "
                         f"({' '.join(str(e).split())[:200]})") from None
    if qp.ndim not in (2, 3) or qp.shape[-1] != 2:
        raise InputError(f"{QUERY_HELP}; got shape {tuple(qp.shape)}")
    if qp.dtype == jnp.bool_ or not (jnp.issubdtype(qp.dtype, jnp.floating) or jnp.issubdtype(qp.dtype, jnp.integer)):
        raise InputError(f"{QUERY_HELP}; got dtype {qp.dtype}")
    if qp.shape[-2] == 0:
        raise InputError(f"{QUERY_HELP}; got no points (shape {tuple(qp.shape)}): pass at least one, "
                         f"or query_points=None for no tracks")
    _check_finite_points(qp)
    return qp.astype(jnp.float32)


def _check_finite_points(qp: jax.Array) -> None:
    """`InputError` naming the first NaN/inf point of `qp` [N, 2] or [B, N, 2] (a NaN
    point would poison the other points' tracks and every visibility). Traced values are
    unknown until the program runs: not checked."""
    try:
        host = np.asarray(qp)
    except jax.errors.TracerArrayConversionError:
        return
    bad = np.argwhere(~np.isfinite(host).all(-1))
    if len(bad):
        at = tuple(int(i) for i in bad[0])
        index = at[0] if len(at) == 1 else at
        raise InputError(f"{QUERY_HELP}; point {index} is {host[at].tolist()} ({len(bad)} non-finite in all): "
                         f"every coordinate must be a finite number")


def check_query_points(query_points: Any, batch: int) -> jax.Array:
    """`as_query_points`, then batched: [N, 2] or [B, N, 2] -> [B, N, 2] float32."""
    qp = as_query_points(query_points)
    if qp.ndim == 2:
        qp = qp[None]
    if qp.shape[0] != batch:
        if qp.shape[0] != 1:
            raise InputError(f"query_points batch {qp.shape[0]} does not match images batch {batch}")
        qp = jnp.broadcast_to(qp, (batch,) + qp.shape[1:])
    return qp


def heads_in_float32(tree: Any) -> Any:
    """`tree` with every floating-point leaf narrower than float32 (bf16, f16) as float32."""
    return jax.tree.map(lambda x: x.astype(jnp.float32) if _is_float(x) and jnp.result_type(x).itemsize < 4
                        else x, tree)


def check_params(params: Params, config: VGGTConfig) -> None:
    """Catch a config that does not describe these params before shapes fail deep inside:
    every parameter the config implies must be in the tree, with its shape (a static
    check of paths and shapes against the converter's layout; no tracing cost). A tree
    without `track_head` is a model without the track head (as `skip_track` loads it);
    extra entries are left alone."""
    try:
        width = params["aggregator"]["camera_token"].shape[-1]
    except (KeyError, TypeError) as e:
        raise InputError("params are not a converted VGGT tree (no aggregator.camera_token); "
                         f"{_layout_hint(config, _expected_params(config, True))}") from e
    if width != config.embed_dim:
        raise InputError(f"params have embed_dim {width} but config says {config.embed_dim}")
    want = _expected_params(config, "track_head" not in params)
    have = flatten_params(params)
    missing = [p for p in want if p not in have]
    wrong = [(p, tuple(np.shape(have[p])), s) for p, s in want.items()
             if p in have and tuple(np.shape(have[p])) != s]
    if not (missing or wrong):
        return
    lines = []
    if missing:
        present = {p[:i] for p in have for i in range(1, len(p) + 1)}
        roots = list(dict.fromkeys(next(p[:i] for i in range(1, len(p) + 1) if p[:i] not in present)
                                   for p in missing))
        lines.append("params lack " + "; ".join(_describe_missing(r, want) for r in roots[:8])
                     + (f"; and {len(roots) - 8} more" if len(roots) > 8 else ""))
    if wrong:
        lines.append("params with the wrong shape: " + "; ".join(
            f"{'.'.join(p)} {have_s}, expected {want_s}" for p, have_s, want_s in wrong[:8])
            + (f"; and {len(wrong) - 8} more" if len(wrong) > 8 else ""))
    parent = roots[0][:-1] if missing else wrong[0][0][:-1]
    raise InputError(". ".join(lines) + ". " + _layout_hint(config, want, parent))


@functools.lru_cache(maxsize=16)
def _expected_params(config: VGGTConfig, skip_track: bool) -> dict[tuple[str, ...], tuple[int, ...]]:
    """{path: shape} of the converted tree `config` implies (cached: a config is hashable)."""
    return expected_param_paths(config, skip_track=skip_track)


def _describe_missing(root: tuple[str, ...], want: dict) -> str:
    under = [p for p in want if p[:len(root)] == root]
    if len(under) == 1 and under[0] == root:
        return f"{'.'.join(root)} (shape {want[root]})"
    return f"{'.'.join(root)} (a sub-tree of {len(under)} parameters, e.g. {'.'.join(under[0])} {want[under[0]]})"


def _layout_hint(config: VGGTConfig, want: dict, parent: tuple[str, ...] = ()) -> str:
    """Which keys the config's layout expects at `parent` (top level by default)."""
    keys = sorted({p[len(parent)] for p in want if p[:len(parent)] == parent and len(p) > len(parent)})
    where = ".".join(parent) or "the top level"
    return (f"the converted VGGT layout for this config (embed_dim {config.embed_dim}, depth {config.depth}; "
            f"rvggt_jax.weights.converter.expected_param_shapes(config), as load_pretrained returns it) "
            f"has at {where}: {', '.join(keys)}")


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


def check_inputs(params: Params, images: Any, config: VGGTConfig, query_points: Any = None
                 ) -> tuple[jax.Array, jax.Array | None]:
    """The checks of a forward's inputs (config, params, images, query points): images as
    [B, S, 3, H, W], query points as [B, N, 2] or None; `InputError` naming the problem."""
    config.validate()
    check_params(params, config)
    images = check_images(images, config)
    if query_points is not None:
        if not config.enable_track or "track_head" not in params:
            raise InputError("query_points given but this model has no track head")
        query_points = check_query_points(query_points, images.shape[0])
    return images, query_points


def forward_frames(params: Params, images: jax.Array, config: VGGTConfig, query_points: jax.Array | None = None,
                   shards: FrameShards | None = None) -> dict[str, Any]:
    """`rvggt_forward` on checked inputs, over the frames of this device: images
    [B, S, 3, H, W] are this device's frames (`shards`, inside `jax.shard_map`; default
    all frames on one device) and so is every per-frame output. Every attention inside
    runs on `config.attention`'s kernel, every float32 matmul at `config.dot_precision`."""
    with config_scope(config):
        return _forward_frames(params, images, config, query_points, shards)


@contextlib.contextmanager
def config_scope(config: VGGTConfig) -> Iterator[None]:
    """Everything traced inside runs on `config.attention`'s kernel with its float32
    matmuls at `config.dot_precision`: what a forward and each Flax part (`model.modules`)
    run under."""
    with kernel_scope(config.attention), precision_scope(config.dot_precision):
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
    readers = {name: (params[name], config.dpt_head.intermediate_layer_idx) for name, on in enabled.items() if on}
    if with_track:
        readers["track_head"] = (params["track_head"]["feature_extractor"], config.track_layer_idx)
    # (a returned layer is projected too, and also kept whole: the heads' values do not
    # depend on which layers are returned)
    raw = {config.depth - 1} if config.enable_camera else set()
    return head_projections(readers, grid, 2 * config.embed_dim, raw, per_group)


def frame_descriptors(patch_tokens: jax.Array, batch: int) -> jax.Array:
    """Place descriptors [B, S, C] of the DINOv2 patch tokens [B*S, h*w, C]: each frame's
    tokens mean-pooled (in float32) and scaled to unit length, so that a dot product is a
    cosine similarity. DINOv2's pooled features are what visual place recognition builds
    on (AnyLoc, SALAD); the long-sequence pipeline proposes loops from them."""
    d = patch_tokens.astype(jnp.float32).mean(axis=1)
    d = d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    return d.reshape(batch, -1, d.shape[-1])


def _forward_frames(params: Params, images: jax.Array, config: VGGTConfig, query_points: jax.Array | None,
                    shards: FrameShards | None) -> dict[str, Any]:
    b, s, _, hh, ww = images.shape
    shards = FrameShards.single(s) if shards is None else shards
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
    agg, patch_tokens, saliency = aggregator_forward(params["aggregator"], images, config, keep, shards, project)

    out: dict[str, Any] = {}
    if config.enable_camera:
        # the camera trunk attends across frames: every device runs it on every frame's
        # camera token (B x S x 2C floats) and keeps its own frames
        cam = shards.gather(agg[config.depth - 1].token(0)[:, :, None], 1)
        pose_enc_list = [shards.local_part(pe, 1) for pe in camera_head(params["camera_head"], cam, config.camera_head)]
        out["pose_enc"] = pose_enc_list[-1]
        out["pose_enc_list"] = pose_enc_list
    out.update(dense_heads({name: params[name] for name, on in enabled.items() if on}, agg, config.dpt_head, grid,
                           per_group))
    if with_track:
        tracks, vis, conf = track_head(params["track_head"], agg, config.track_head_config, grid, query_points,
                                       shards=shards, remat=per_group)
        out["track"], out["vis"], out["conf"] = tracks[-1], vis, conf
    if config.return_images:
        # A copy of the input (an argument cannot be an output): made from the last head
        # output (x 1, exact) so that XLA makes it at the end, not at the program start
        # where it would sit through the whole forward.
        last = jax.tree.leaves(out)
        unit = unit_images(images)
        out["images"] = unit * (1.0 + zeros_from((), jnp.float32, last[-1])) if last else unit
    if config.return_saliency:
        out["saliency"], out["patch_tokens"] = saliency, patch_tokens
    if config.return_descriptors:
        out["descriptors"] = frame_descriptors(patch_tokens, b)
    for i in config.return_layers:
        out[f"aggregated_{i:02d}"] = agg[i].array()

    if "depth" in out:
        chex.assert_shape(out["depth"], (b, s, hh, ww, 1))
    return out
