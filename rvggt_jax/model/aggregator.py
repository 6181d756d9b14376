"""The alternating-attention aggregator: `depth` frame blocks interleaved with `depth`
global blocks over camera, register and patch tokens.

Frame blocks attend within each frame ([B*S, P, C]); global blocks attend across the
whole sequence ([B, S*P, C]) and are where RegimeVGGT compresses (`compression.global_block`).
"""

from __future__ import annotations

import dataclasses
from typing import Iterable

import chex
import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops import chunks

from rvggt_jax import compression

from rvggt_jax.model import layers
from rvggt_jax.config import VGGTConfig
from rvggt_jax.ops.shards import FrameShards
from rvggt_jax.model.layers import Params
from rvggt_jax.model.patch_embed import patch_embed_tokens


@jax.tree_util.register_pytree_node_class
class KeptLayer:
    """The tokens of one kept aggregator layer, [B, S, P, 2C] float32 on demand, without a
    copy: its frame-block and global-block halves stay where the aggregator left them and
    are sliced and concatenated per group of frames where a head reads them (`frames`).
    At 1000 frames of VGGT-1B every full copy of the four kept layers costs 17 GB in
    bfloat16.

    Each half is a slot of a stacked [K, B, S, P, C] buffer (compute dtype; 16-bit ones as
    `chunks.Bits16`): the frame half in slot `slot`, the global half in `global_slot`
    (default the same). The last layer's global half is the aggregator's final residual
    stream itself ([1, B, S, P, C] float32, slot 0), read rounded to `dtype` (the compute
    dtype), the values its slot would have held."""

    def __init__(self, frame_buf, global_buf, slot: int, global_slot: int | None = None, dtype=None):
        self.frame_buf, self.global_buf, self.slot = frame_buf, global_buf, slot
        self.global_slot = slot if global_slot is None else global_slot
        self.dtype = None if dtype is None else jnp.dtype(dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.frame_buf.shape[1:-1] + (2 * self.frame_buf.shape[-1],)

    @property
    def ndim(self) -> int:
        return 4

    def _read(self, op, *index) -> jax.Array:
        """op(buffer, slot, *index) on both halves, concatenated along channels, float32."""
        halves = [chunks.read_buffer(self.frame_buf, lambda b, *i: op(b, self.slot, *i), *index),
                  chunks.read_buffer(self.global_buf, lambda b, *i: op(b, self.global_slot, *i), *index)]
        if self.dtype is not None:  # (the residual stream, as its slot would hold it)
            halves[1] = halves[1].astype(self.dtype)
        # (the barrier keeps the float32 cast on the slices)
        return jnp.concatenate(jax.lax.optimization_barrier(halves), axis=-1).astype(jnp.float32)

    def frames(self, start: jax.Array | int, count: int) -> jax.Array:
        """Frames [start, start + count) of the flattened B*S frames: [count, P, 2C] float32."""
        def part(buf, slot, start):
            # (buf: float32, or a 16-bit buffer's bits; plain slices, which also carry
            # the derivatives of `chunks.Bits16`)
            flat = buf.reshape((buf.shape[0], -1) + buf.shape[3:])  # [K, B*S, P, C]
            # Frames first, then the slot, both dynamic slices: a static slot slice is
            # loop-invariant and XLA would hoist it (cast to float32) out of the heads'
            # loop, a float32 copy of every kept layer (34 GB at 1000 frames of VGGT-1B).
            frames = jax.lax.dynamic_slice_in_dim(flat, start, count, 1)
            return jax.lax.dynamic_index_in_dim(frames, slot, 0, keepdims=False)

        return self._read(part, start)

    def token(self, index: int) -> jax.Array:
        """One token of every frame: [B, S, 2C] float32 (index 0: the camera token)."""
        return self._read(lambda buf, slot: buf[slot, :, :, index])

    def array(self) -> jax.Array:
        """The whole layer [B, S, P, 2C] float32 (a copy)."""
        return self._read(lambda buf, slot: buf[slot])

    def tree_flatten(self):
        return (self.frame_buf, self.global_buf), (self.slot, self.global_slot, self.dtype)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children, *aux)


def special_tokens(token: jax.Array, b: int, frame_ids: jax.Array) -> jax.Array:
    """Upstream's first-frame/other-frames token pair [1, 2, X, C] -> [B*S, X, C] for the
    frames `frame_ids` [S] (global indices): frame 0 takes entry 0, every other frame
    entry 1."""
    s = frame_ids.shape[0]
    pick = jnp.where((frame_ids == 0)[:, None, None], token[0, 0], token[0, 1])  # [S, X, C]
    return jnp.broadcast_to(pick[None], (b,) + pick.shape).reshape((b * s,) + token.shape[2:])


def aggregator_forward(
    p: Params, images: jax.Array, config: VGGTConfig, keep_layers: Iterable[int],
    shards: FrameShards | None = None,
) -> tuple[dict[int, jax.Array], jax.Array, jax.Array]:
    """images [B, S, 3, H, W] in [0, 1] ->
    (outputs {layer: `KeptLayer` (tokens [B, S, P, 2C])} for the layers in `keep_layers`,
     patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w]).

    Each output concatenates the frame-block and global-block outputs of that layer; the
    other layers' outputs are never materialised beyond their use.

    With `shards` (frames split over devices, inside `jax.shard_map`): S is this device's
    frames, every output holds them; the global blocks attend across all devices."""
    b, s, _, hh, ww = images.shape
    shards = FrameShards.single(s) if shards is None else shards
    if s != shards.local:
        raise ValueError(f"{s} frames on this device but the shards say {shards.local}")
    ps = config.patch_size
    h, w = hh // ps, ww // ps
    c = config.embed_dim
    keep = set(keep_layers)

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
    chex.assert_shape(tokens, (b * s, config.patch_start_idx + h * w, c))

    geom = compression.Geometry(shards.frames, h, w, config.patch_start_idx)
    outputs = _layers(p, tokens, saliency, geom, config, shards, sorted(keep))
    return outputs, patch_tokens, saliency


def layer_groups(config: VGGTConfig, geom: compression.Geometry) -> tuple[tuple[int, ...], ...]:
    """Runs of consecutive layers whose global blocks share one static plan: each run is
    one `lax.scan`. Dense: one run of every layer. A band's first layer (it computes the
    match) is a run apart from the layers that reuse it: inside their scan it would be a
    `lax.cond` reading the residual stream, and XLA then copies the stream for the
    in-place update after it (4 GB per layer at 1000 frames of VGGT-1B)."""
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


def kept_slots(depth: int, keep) -> tuple[np.ndarray, int]:
    """(slot [depth] of every layer's outputs, number of spare slots). Kept layer keep[j]
    owns slot j; any other layer writes to the slot of the next kept layer, which that
    layer overwrites later in the same loop. Only layers after the last kept one need a
    spare slot (K + 1): at 1000 frames of VGGT-1B a slot is 4 GB in bfloat16."""
    keep = sorted(keep)
    slot = np.zeros(depth, np.int32)
    spare = int(not keep or keep[-1] < depth - 1)
    for i in range(depth):
        later = [j for j, k in enumerate(keep) if k >= i]
        slot[i] = later[0] if later else len(keep)
    return slot, spare


def _layers(p: Params, tokens: jax.Array, saliency: jax.Array, geom: compression.Geometry, config: VGGTConfig,
            shards: FrameShards, keep: list[int]) -> dict[int, KeptLayer]:
    """The 2 x depth blocks over tokens [B*S, P, C] (this device's S frames of the
    sequence `geom`) as one `lax.scan` per run of layers sharing a static global
    plan (`layer_groups`: one run for dense, ~7 for `regime`). A scan compiles one body per
    run instead of one per layer (~10x less compile time) and, above all, confines every
    temporary of a layer to its loop body: unrolled layers let XLA hoist each layer's
    zero-initialised buffers to the start of the program, all alive at once (3.7x the
    memory of dense at 100 frames of VGGT-1B before this).

    The kept layers' frame and global halves go to two [K, B, S, P, C] buffers in the
    compute dtype (what the heads read), every layer writing its outputs to a slot
    (`kept_slots`), so the body is the same unconditional in-place write for every
    layer. Except: a kept last layer's global half is the final residual stream (its
    `KeptLayer` reads x), so the global buffer has one slot less and the layers after the
    last-but-one kept layer, a scan of their own, write no global half."""
    n, num_tokens, c = tokens.shape
    s = shards.local  # frames here (geom.frames: in the sequence)
    b = n // s
    dtype = config.compute_dtype
    # RoPE tables, built once for all blocks: [1, P, 1, D] and [1, S*P, 1, D] (periodic
    # when long: `RopeTables.of_sequence`)
    frame_pos = layers.RopeTables.from_positions(
        jnp.asarray(layers.patch_positions(geom.h, geom.w, geom.num_special))[None], config.head_dim,
        config.rope_freq)
    global_pos = layers.RopeTables.of_sequence(frame_pos, s)
    slot, spare = kept_slots(config.depth, keep)
    state = None
    if not config.compression.is_dense:
        # (the state is sequence-wide: every device holds all of it, built from every
        # frame's saliency, a few floats per patch)
        state = compression.init_state(config.compression, shards.gather(saliency, 1), geom, shards)

    x = tokens.reshape(b, s * num_tokens, c)
    # Made after the patch embed, from its saliency: a constant buffer would be allocated
    # at the program start, alive through the patch embed (chunks.zeros_after). Not from
    # the tokens: XLA folds the zeros into the first layer's write, which would keep the
    # tokens alive (and copied) through that layer. Two distinct values: one buffer for
    # both would make XLA copy it inside the layer loop.
    shape = (len(keep) + spare, b, s, num_tokens, c)
    kept_frame = _kept_buffer(shape, dtype, saliency)
    # The last layer's global half, when kept, is the final residual stream itself: no
    # slot for it, and the layers after the last-but-one kept layer write no global half
    # (a slot nobody reads until the last layer fills it: 2.1 GB at 1000 frames of
    # VGGT-1B in bfloat16, alive through every layer, where the aggregator peaks)
    last_is_x = bool(keep) and keep[-1] == config.depth - 1
    writes_global = (keep[-2] if len(keep) > 1 else -1) if last_is_x else config.depth - 1  # up to this layer
    n_global = shape[0] - int(last_is_x)
    kept_global = _kept_buffer((n_global,) + shape[1:], dtype, jax.tree.leaves(kept_frame)[0]) if n_global else None
    groups = [g for run in layer_groups(config, geom)
              for g in (tuple(i for i in run if i <= writes_global), tuple(i for i in run if i > writes_global)) if g]
    for group in groups:
        # a group of layers that compute and store a band's match carries the last one out
        plan0 = compression.layer_plan(config.compression, group[0], geom)
        band = _storing(plan0) if state is not None else False
        key = plan0.match_key

        def layer(carry, xs_i, group=group, band=band, key=key, store=group[0] <= writes_global):
            x, kept_frame, kept_global, cached = carry
            i, k = xs_i
            p_frame = layers.select_block(p["frame_blocks"], group, i)
            p_global = layers.select_block(p["global_blocks"], group, i)
            x = layers.block(p_frame, x.reshape(b * s, num_tokens, c), config.num_heads, frame_pos,
                             config.rope_freq, dtype=dtype)
            kept_frame = _write_slot(kept_frame, x.reshape(b, s, num_tokens, c), k, dtype)
            x = x.reshape(b, s * num_tokens, c)
            if state is None:
                x = compression.dense_global_block(p_global, x, global_pos, config, shards, num_tokens)
            else:
                x, after = compression.global_block(p_global, x, global_pos, group[0], config, state)
                if band:
                    cached = after.matches[key]
            if store:
                kept_global = _write_slot(kept_global, x.reshape(b, s, num_tokens, c), k, dtype)
            return (x, kept_frame, kept_global, cached), None

        if config.remat:  # keep only the layer's inputs for the backward pass (config.remat)
            layer = jax.checkpoint(layer)
        cached = compression.Match.zeros(plan0, b) if band else None
        xs = (jnp.arange(len(group)), jnp.asarray(slot[list(group)]))
        (x, kept_frame, kept_global, cached), _ = jax.lax.scan(layer, (x, kept_frame, kept_global, cached), xs)
        if band:
            state = state.with_match(key, cached)
    out = {i: KeptLayer(kept_frame, kept_global, j) for j, i in enumerate(keep)}
    if last_is_x:
        out[keep[-1]] = KeptLayer(kept_frame, x.reshape(1, b, s, num_tokens, c), len(keep) - 1, 0, dtype)
    return out


def _kept_buffer(shape: tuple[int, ...], dtype, dep: jax.Array):
    """Zeros for the kept layers' halves [K, B, S, P, C]: 16-bit ones as bits
    (`chunks.Bits16`: the heads slice them in a loop without a copy of the whole)."""
    if jnp.dtype(dtype).itemsize == 2:
        return chunks.Bits16.zeros_after(shape, dtype, dep)
    return chunks.zeros_after(shape, dtype, dep)


def _write_slot(buf, x: jax.Array, k: jax.Array, dtype):
    """buf with slot k set to x in the compute dtype (in place). (lax's dynamic update,
    not .at[k].set: the latter is a scatter that XLA lowers with a bounds check, out of
    place: a copy of the kept buffer per step.)"""
    if isinstance(buf, chunks.Bits16):
        return buf.update_index(x, k)
    return jax.lax.dynamic_update_index_in_dim(buf, x.astype(dtype), k, 0)
