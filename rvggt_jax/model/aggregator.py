"""The alternating-attention aggregator: `depth` frame blocks interleaved with `depth`
global blocks over camera, register and patch tokens.

Frame blocks attend within each frame ([B*S, P, C]); global blocks attend across the
whole sequence ([B, S*P, C]): dense ones are `layers.dense_global_block`, and
RegimeVGGT's compressed ones `compression.global_block`. The layers the heads read are
returned as `KeptLayer`s (`kept.py`).
"""

from __future__ import annotations

import dataclasses
from typing import Iterable, Mapping, NamedTuple

import chex
import jax
import jax.numpy as jnp

from rvggt_jax import compression
from rvggt_jax.config import VGGTConfig
from rvggt_jax.model import layers, remat
from rvggt_jax.model.kept import KeptLayer, KeptLayers, ProjectedLayer, Projection, weights_after
from rvggt_jax.model.params import Params
from rvggt_jax.model.patch_embed import patch_embed_tokens
from rvggt_jax.ops.shards import frame_layout


def special_tokens(token: jax.Array, b: int, frame_ids: jax.Array) -> jax.Array:
    """Upstream's first-frame/other-frames token pair [1, 2, X, C] -> [B*S, X, C] for the
    frames `frame_ids` [S] (global indices): frame 0 takes entry 0, every other frame
    entry 1."""
    s = frame_ids.shape[0]
    pick = jnp.where((frame_ids == 0)[:, None, None], token[0, 0], token[0, 1])  # [S, X, C]
    return jnp.broadcast_to(pick[None], (b,) + pick.shape).reshape((b * s,) + token.shape[2:])


def aggregator_forward(
    p: Params, images: jax.Array, config: VGGTConfig, keep_layers: Iterable[int],
    project: Mapping[int, Projection] | None = None,
) -> tuple[dict[int, KeptLayer | ProjectedLayer], jax.Array, jax.Array]:
    """images [B, S, 3, H, W] in [0, 1] -> ({layer: `KeptLayer` [B, S, P, 2C]} for
    `keep_layers` and {layer: `ProjectedLayer`} for `project` (its `raw` the `KeptLayer`
    when kept too), patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w]).

    Upstream's loop: patch embed, RoPE tables, then per layer a frame block and a global
    block (dense, or RegimeVGGT's under the compression state), as one `lax.scan` per run
    of layers sharing a static global plan (`layer_groups`); `kept.KeptLayers` decides
    where the kept layers go. With the frames split over devices (`ops.shards.frame_layout`),
    S is this device's frames and the global blocks attend across all devices."""
    stream, patch_tokens, saliency = aggregator_start(p, images, config)
    out = aggregator_layers(p, stream, config, keep_layers, project, images.shape[-2:], saliency)
    return out, patch_tokens, saliency


class Stream(NamedTuple):
    """The aggregator before its first layer: the residual stream x [B, S*P, C] and the
    compression state (None when dense)."""

    x: jax.Array
    state: compression.State | None


def aggregator_start(p: Params, images: jax.Array, config: VGGTConfig) -> tuple[Stream, jax.Array, jax.Array]:
    """The aggregator before its first layer: (the `Stream` of the input tokens,
    patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w])."""
    b, s, _, hh, ww = images.shape
    tokens, patch_tokens, saliency = input_tokens(p, images, config)
    state = None
    if not config.compression.is_dense:
        # (sequence-wide: every device holds all of it, from every frame's saliency)
        layout = frame_layout(s)
        state = compression.init_state(config.compression, layout.gather(saliency, 1),
                                       _geometry(config, layout.frames, (hh, ww)))
    return Stream(tokens.reshape(b, -1, tokens.shape[-1]), state), patch_tokens, saliency


def aggregator_layers(
    p: Params, stream: Stream, config: VGGTConfig, keep_layers: Iterable[int],
    project: Mapping[int, Projection] | None, image_hw: tuple[int, int], dep: jax.Array,
    layers: range | None = None,
) -> dict[int, KeptLayer | ProjectedLayer]:
    """The aggregator's layers 0.. up to the last of `layers` (default: all of them) from
    `stream` -> the kept and projected layers among them, as `aggregator_forward` returns
    them. `layers` may end only after a projected layer, where a scan ends (the
    low-memory mode's part 1, `model.low_memory`). `dep`: the kept buffers are made
    after it (docs/memory_layout.md)."""
    x, state = stream
    c = x.shape[-1]
    geom = _geometry(config, frame_layout(_frames(x, config, image_hw)).frames, image_hw)
    b, s = x.shape[0], x.shape[1] // geom.per_frame
    shape = (b, s, geom.per_frame, c)  # (B, S, P, C)
    project = dict(project or {})
    pos = rope_tables(geom, config, s)
    kept = KeptLayers.start(config.depth, keep_layers, project, shape, config.compute_dtype, dep)
    projected = {}
    for group in kept.scans(layer_groups(config, geom)):
        if layers is not None:
            if not set(group) <= set(layers):
                if set(group) & set(layers):
                    raise ValueError(f"layers {layers} cut the scan of layers {group}")
                continue
        x, kept, state = _scan_layers(p, x, kept, group, pos, geom, config, state)
        if group[-1] in project:
            kept, projected[group[-1]], after = kept.project(group[-1], x, project[group[-1]], shape)
            p = weights_after(p, after)
    out = kept.outputs(x, shape) if layers is None or config.depth - 1 in layers else {}
    for i, layer in projected.items():
        out[i] = ProjectedLayer(layer.buf, layer.columns, layer.batch, out.get(i), layer.tokens)
    return out


def _geometry(config: VGGTConfig, frames: int, image_hw: tuple[int, int]) -> compression.Geometry:
    """The global blocks' sequence: `frames` frames (of the whole sequence) of
    `image_hw` images."""
    hh, ww = image_hw
    return compression.Geometry(frames, hh // config.patch_size, ww // config.patch_size, config.patch_start_idx)


def _frames(x: jax.Array, config: VGGTConfig, image_hw: tuple[int, int]) -> int:
    """This device's frames in the stream x [B, S*P, C]."""
    return x.shape[1] // _geometry(config, 1, image_hw).per_frame


def input_tokens(p: Params, images: jax.Array, config: VGGTConfig) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The aggregator's input: (tokens [B*S, P, C] = camera, registers and DINO patch
    tokens of every frame, patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w])."""
    b, s, _, hh, ww = images.shape
    ps = config.patch_size
    dino, num_prefix, saliency = patch_embed_tokens(p["patch_embed"], images, config)
    patch_tokens = dino[:, num_prefix:]
    frame_ids = frame_layout(s).frame_ids()
    special = jnp.concatenate([special_tokens(p["camera_token"], b, frame_ids),
                               special_tokens(p["register_token"], b, frame_ids)], axis=1).astype(dino.dtype)
    if num_prefix == special.shape[1]:
        # DINO's [CLS] + registers and our camera + registers are equally many: the special
        # tokens replace them in DINO's own buffer (no second [B*S, P, C] float32 copy)
        tokens = jax.lax.dynamic_update_slice_in_dim(dino, special, 0, axis=1)
    else:
        tokens = jnp.concatenate([special, patch_tokens], axis=1)
    chex.assert_shape(tokens, (b * s, config.patch_start_idx + (hh // ps) * (ww // ps), config.embed_dim))
    return tokens, patch_tokens, saliency


def layer_groups(config: VGGTConfig, geom: compression.Geometry) -> tuple[tuple[int, ...], ...]:
    """Runs of consecutive layers whose global blocks share one static plan: each run is
    one `lax.scan`. Dense: one run of every layer. A band's first layer (it computes the
    match) is a run apart from the layers that reuse it (inside their scan it would be a
    `lax.cond` reading the residual stream: a copy of the stream for the update after it)."""
    if config.compression.is_dense:
        return (tuple(range(config.depth)),)
    plans = [_plan(config, i, geom) for i in range(config.depth)]
    groups: list[list[int]] = []
    for i, plan in enumerate(plans):
        if groups and plans[groups[-1][-1]] == plan:
            groups[-1].append(i)
        else:
            groups.append([i])
    return tuple(tuple(g) for g in groups)


def _plan(config: VGGTConfig, layer: int, geom: compression.Geometry):
    """The layer's static global plan with the layer index blanked (for comparison)."""
    return dataclasses.replace(compression.layer_plan(config.compression, layer, geom), layer=0)


def _storing(plan) -> bool:
    return plan.kind == compression.LayerKind.MERGE and plan.match == "compute" and plan.match_key is not None


def rope_tables(geom: compression.Geometry, config: VGGTConfig, frames: int
                ) -> tuple[layers.RopeTables, layers.RopeTables]:
    """The RoPE tables of every block, built once: one frame's [1, P, 1, D] and the
    sequence's [1, frames * P, 1, D] (one frame's rows, `chunks.Periodic`: `RopeTables.of_sequence`).

    They are constants of the program, computed while tracing (the positions are static),
    so no block recomputes the trigonometry per token (docs/history/cpu_speed.md,
    "Trigonometry per token")."""
    with jax.ensure_compile_time_eval():
        frame_pos = layers.RopeTables.from_positions(
            jnp.asarray(layers.patch_positions(geom.h, geom.w, geom.num_special))[None], config.head_dim,
            config.rope_freq)
    return frame_pos, layers.RopeTables.of_sequence(frame_pos, frames)


def _scan_layers(p: Params, x: jax.Array, kept: KeptLayers, group: tuple[int, ...], pos: tuple,
                 geom: compression.Geometry, config: VGGTConfig, state):
    """The layers `group` (one static global plan) as one `lax.scan` over
    (x [B, S*P, C], the kept layers): each layer a frame block, its output kept, then a
    global block (dense, or under the compression `state`), kept too when the kept
    layers store global halves there. Returns (x, kept, state), the state with the band's
    match when the group computes and stores one."""
    b, n, c = x.shape
    num_tokens = geom.per_frame
    s = n // num_tokens
    frame_pos, global_pos = pos
    cfg = layers.BlockConfig.of(config)
    store = kept.stores_global(group)
    # a group of layers that compute and store a band's match carries the last one out
    plan0 = compression.layer_plan(config.compression, group[0], geom)
    band = _storing(plan0) if state is not None else False
    key = plan0.match_key

    def layer(carry, xs_i):
        x, kept, cached = carry
        i, k = xs_i
        p_frame = layers.select_block(p["frame_blocks"], group, i)
        p_global = layers.select_block(p["global_blocks"], group, i)
        x = layers.sequence_block(p_frame, x.reshape(b * s, num_tokens, c), frame_pos, cfg)
        kept = kept.after_frame_block(x.reshape(b, s, num_tokens, c), k)
        x, kept, p_global = kept.before_global_block(x, p_global, single=len(group) == 1)
        x = x.reshape(b, s * num_tokens, c)
        if state is None:
            x = layers.dense_global_block(p_global, x, global_pos, config, num_tokens)
        else:
            x, after = compression.global_block(p_global, x, global_pos, group[0], config, state)
            if band:
                cached = after.matches[key]
        kept = kept.after_global_block(x.reshape(b, s, num_tokens, c), k, store)
        return (x, kept, cached), None

    # a training step keeps only the layer's inputs for the backward pass (config.remat)
    layer = remat.checkpoint(layer, config, "block")
    cached = compression.Match.zeros(plan0, b) if band else None
    xs = (jnp.arange(len(group)), kept.slots_of(group))
    (x, kept, cached), _ = jax.lax.scan(layer, (x, kept, cached), xs)
    if band:
        state = state.with_match(key, cached)
    return x, kept, state
