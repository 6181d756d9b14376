"""The alternating-attention aggregator: `depth` frame blocks interleaved with `depth`
global blocks over camera, register and patch tokens.

Frame blocks attend within each frame ([B*S, P, C]); global blocks attend across the
whole sequence ([B, S*P, C]): dense ones are `global_block.dense_global_block`, and
RegimeVGGT's compressed ones `compression.global_block`. The layers the heads read are
returned as `KeptLayer`s (`kept.py`).
"""

from __future__ import annotations

import dataclasses
from typing import Iterable, Mapping

import chex
import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax import compression
from rvggt_jax.config import VGGTConfig
from rvggt_jax.model import layers, remat
from rvggt_jax.model.global_block import dense_global_block
from rvggt_jax.model.kept import (KeptLayer, ProjectedLayer, Projection, kept_buffer, kept_slots, project_layer,
                                  stored, write_slot)
from rvggt_jax.model.params import Params
from rvggt_jax.model.patch_embed import patch_embed_tokens
from rvggt_jax.ops.ordering import with_dependency
from rvggt_jax.ops.shards import FrameShards


def special_tokens(token: jax.Array, b: int, frame_ids: jax.Array) -> jax.Array:
    """Upstream's first-frame/other-frames token pair [1, 2, X, C] -> [B*S, X, C] for the
    frames `frame_ids` [S] (global indices): frame 0 takes entry 0, every other frame
    entry 1."""
    s = frame_ids.shape[0]
    pick = jnp.where((frame_ids == 0)[:, None, None], token[0, 0], token[0, 1])  # [S, X, C]
    return jnp.broadcast_to(pick[None], (b,) + pick.shape).reshape((b * s,) + token.shape[2:])


def aggregator_forward(
    p: Params, images: jax.Array, config: VGGTConfig, keep_layers: Iterable[int],
    shards: FrameShards | None = None, project: Mapping[int, Projection] | None = None,
) -> tuple[dict[int, KeptLayer | ProjectedLayer], jax.Array, jax.Array]:
    """images [B, S, 3, H, W] in [0, 1] ->
    (outputs {layer: `KeptLayer` (tokens [B, S, P, 2C])} for the layers in `keep_layers`,
     and {layer: `ProjectedLayer`} for the layers in `project` (its `raw` the
     `KeptLayer` when the layer is in `keep_layers` too),
     patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w]).

    Each output concatenates the frame-block and global-block outputs of that layer; the
    other layers' outputs are never materialised beyond their use. The 2 x depth blocks
    run as one `lax.scan` per run of layers sharing a static global plan (`layer_groups`:
    one run for dense, ~7 for `regime`): one compiled body per run, and every temporary
    of a layer confined to its loop body. The kept layers' frame and global halves go to
    two [K, B, S, P, C] buffers in the compute dtype (`kept.py`); a kept last layer's
    global half is the final residual stream (its `KeptLayer` reads x), so the global
    buffer has one slot less and the layers after the last-but-one kept layer, a scan of
    their own, write no global half.

    A layer in `project` (`kept.Projection`: its readers' first step, e.g. the DPT heads'
    norm and projection) ends its scan; the projection then reads its halves from the
    slots it wrote (its global half from the stream after the last-but-one kept layer),
    before the next layer overwrites them (`kept.project_layer`). Unless it is in
    `keep_layers` too, it takes no slot of its own.

    With `shards` (frames split over devices, inside `jax.shard_map`): S is this device's
    frames, every output holds them; the global blocks attend across all devices."""
    b, s, _, hh, ww = images.shape
    shards = FrameShards.single(s) if shards is None else shards
    if s != shards.local:
        raise ValueError(f"{s} frames on this device but the shards say {shards.local}")
    keep = sorted(set(keep_layers))
    tokens, patch_tokens, saliency = input_tokens(p, images, config, shards)
    num_tokens, c = tokens.shape[1:]
    geom = compression.Geometry(shards.frames, hh // config.patch_size, ww // config.patch_size,
                                config.patch_start_idx)
    dtype = config.compute_dtype
    pos = rope_tables(geom, config, s)
    slot, spare = kept_slots(config.depth, keep)
    state = None
    if not config.compression.is_dense:
        # (the state is sequence-wide: every device holds all of it, built from every
        # frame's saliency, a few floats per patch)
        state = compression.init_state(config.compression, shards.gather(saliency, 1), geom, shards)

    x = tokens.reshape(b, s * num_tokens, c)
    # (the buffers made from the saliency, after the patch embed; two distinct values,
    # one buffer each: docs/memory_layout.md)
    shape = (len(keep) + spare, b, s, num_tokens, c)
    kept_frame = kept_buffer(shape, dtype, saliency)
    last_is_x = bool(keep) and keep[-1] == config.depth - 1
    writes_global = (keep[-2] if len(keep) > 1 else -1) if last_is_x else config.depth - 1  # up to this layer
    n_global = shape[0] - int(last_is_x)
    if not keep:  # (every layer read is projected: no halves to keep)
        writes_global, n_global = -1, 0
    kept_global = kept_buffer((n_global,) + shape[1:], dtype, jax.tree.leaves(kept_frame)[0]) if n_global else None
    project = dict(project or {})
    groups = [g for run in layer_groups(config, geom)
              for g in (tuple(i for i in run if i <= writes_global), tuple(i for i in run if i > writes_global)) if g]
    groups = [g for run in groups for g in _split_after(run, project)]
    carry = (x, kept_frame, kept_global)
    projected = {}
    for group in groups:
        carry, state = _scan_layers(p, carry, group, slot, pos, geom, config, shards, state,
                                    store=group[0] <= writes_global)
        if group[-1] in project:
            # the layer as its slots hold it now (every layer up to writes_global writes its
            # global half too): the next layer overwrites them, in the buffers the
            # projection's loop returns
            x, kept_frame, kept_global = carry
            i, k = group[-1], int(slot[group[-1]])
            if i <= writes_global:
                layer = KeptLayer(kept_frame, kept_global, k)
            else:  # (no global slot: the global half is the stream, which the loop only reads)
                layer = KeptLayer(kept_frame, x.reshape(1, b, s, num_tokens, c), k, 0, dtype)
            projected[i], layer = project_layer(layer, project[i], dtype, clear=i not in keep)
            carry = (x, layer.frame_buf, layer.global_buf if i <= writes_global else kept_global)
            if i in keep or i > writes_global:
                # a buffer the loop only reads: the next scan starts after it through one
                # weight (a dependency of the stream, x + 0, gets a buffer of its own)
                p = _after(p, stored(projected[i]))
    x, kept_frame, kept_global = carry
    out = {i: KeptLayer(kept_frame, kept_global, j) for j, i in enumerate(keep)}
    if last_is_x:
        out[keep[-1]] = KeptLayer(kept_frame, x.reshape(1, b, s, num_tokens, c), len(keep) - 1, 0, dtype)
    for i, buf in projected.items():
        out[i] = ProjectedLayer(buf, project[i].columns, (b, s), out.get(i))
    return out, patch_tokens, saliency


def _split_after(run: tuple[int, ...], project) -> list[tuple[int, ...]]:
    """A run of layers cut after each layer in `project`: its projection runs between
    two scans."""
    parts, part = [], []
    for i in run:
        part.append(i)
        if i in project:
            parts.append(tuple(part))
            part = []
    return parts + ([tuple(part)] if part else [])


def _after(p: Params, dep: jax.Array) -> Params:
    """The aggregator's weights with the frame blocks' smallest weight computed from
    `dep` (the next scan, which takes it, starts after `dep` exists)."""
    frame = p["frame_blocks"]
    leaves, tree = jax.tree.flatten(frame)
    small = min(range(len(leaves)), key=lambda k: leaves[k].size)
    leaves[small] = with_dependency(leaves[small], dep)
    return {**p, "frame_blocks": jax.tree.unflatten(tree, leaves)}


def input_tokens(p: Params, images: jax.Array, config: VGGTConfig, shards: FrameShards
                 ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The aggregator's input: (tokens [B*S, P, C] = camera, registers and DINO patch
    tokens of every frame, patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w])."""
    b, s, _, hh, ww = images.shape
    ps = config.patch_size
    dino, num_prefix, saliency = patch_embed_tokens(p["patch_embed"], images, config)
    patch_tokens = dino[:, num_prefix:]
    frame_ids = shards.frame_ids()
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
    `lax.cond` reading the residual stream, which XLA copies for the update after it)."""
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

    They are constants of the program, computed by XLA while tracing (the positions are
    static). Computed inside the program, cos and sin were fused into their consumers
    outside the layer loops (the blocks a plan runs once), which took them again for every
    token: at 64 frames of `regime` in the speed layout, six [S*P, D] fusions of the merged
    Q/K took 1.1-2.3 ms each instead of ~0.15 ms (docs/benchmarks.md)."""
    with jax.ensure_compile_time_eval():
        frame_pos = layers.RopeTables.from_positions(
            jnp.asarray(layers.patch_positions(geom.h, geom.w, geom.num_special))[None], config.head_dim,
            config.rope_freq)
    return frame_pos, layers.RopeTables.of_sequence(frame_pos, frames)


def _scan_layers(p: Params, carry: tuple, group: tuple[int, ...], slot: np.ndarray, pos: tuple,
                 geom: compression.Geometry, config: VGGTConfig, shards: FrameShards, state, store: bool):
    """The layers `group` (one static global plan) as one `lax.scan` over
    carry = (x [B, S*P, C], kept frame halves, kept global halves): each layer a frame
    block, its output written to its kept slot, then a global block (dense, or under the
    compression `state`), written too when `store`. Returns (carry, state), the state
    with the band's match when the group computes and stores one."""
    x = carry[0]
    b, n, c = x.shape
    s = shards.local
    num_tokens = n // s
    dtype = config.compute_dtype
    frame_pos, global_pos = pos
    # a group of layers that compute and store a band's match carries the last one out
    plan0 = compression.layer_plan(config.compression, group[0], geom)
    band = _storing(plan0) if state is not None else False
    key = plan0.match_key

    def layer(carry, xs_i):
        x, kept_frame, kept_global, cached = carry
        i, k = xs_i
        p_frame = layers.select_block(p["frame_blocks"], group, i)
        p_global = layers.select_block(p["global_blocks"], group, i)
        x = layers.block(p_frame, x.reshape(b * s, num_tokens, c), config.num_heads, frame_pos,
                         config.rope_freq, dtype=dtype)
        kept_frame = write_slot(kept_frame, x.reshape(b, s, num_tokens, c), k, dtype)
        # the global block updates x in place: after the kept write has read it (else XLA
        # copies the 4 GiB stream at 1000 frames for the write; docs/memory_layout.md).
        # The order comes through the block's weights, not as x + 0: XLA:GPU gave that
        # sum a buffer of its own, a second stream.
        if len(group) == 1:
            # a run of one layer is no loop: its slot is a constant, and XLA reads the
            # zero from x itself, not from the written buffer (XLA:GPU moved the write
            # after `regime`'s first global block and copied the stream for it)
            x, kept_frame = jax.lax.optimization_barrier((x, kept_frame))
        x = x.reshape(b, s * num_tokens, c)
        p_global = jax.tree.map(lambda w: with_dependency(w, stored(kept_frame)), p_global)
        if state is None:
            x = dense_global_block(p_global, x, global_pos, config, shards, num_tokens)
        else:
            x, after = compression.global_block(p_global, x, global_pos, group[0], config, state)
            if band:
                cached = after.matches[key]
        if store:
            kept_global = write_slot(kept_global, x.reshape(b, s, num_tokens, c), k, dtype)
        return (x, kept_frame, kept_global, cached), None

    # a training step keeps only the layer's inputs for the backward pass (config.remat)
    layer = remat.checkpoint(layer, config, "block")
    cached = compression.Match.zeros(plan0, b) if band else None
    xs = (jnp.arange(len(group)), jnp.asarray(slot[list(group)]))
    (x, kept_frame, kept_global, cached), _ = jax.lax.scan(layer, (*carry, cached), xs)
    if band:
        state = state.with_match(key, cached)
    return (x, kept_frame, kept_global), state
