"""The compressed global block and its per-forward state.

    state = init_state(config.compression, saliency, geometry, shards)   # once per forward
    x, state = global_block(p_block, x, pos, layer, config, state)

`layer` is a Python int: every layer has its own static plan (`plan.layer_plan`, computed
once per call and passed to every helper) and the state may gain entries (the band
caches) from one layer to the next. Nothing branches on data: every shape comes from
(x.shape, geometry, configuration). The block checks its operands' shapes against the
plan at trace time, so the plan (what `cost.py` and the tests read) is what runs.

The state is a `State` (a pytree; geometry and shards static): the protection flags, the
band-aligned match cache {cache key: `Match`} and the K/V slots of cached matches
{(cache key, tile): `KVSlots`}.

Split over devices (`FrameShards`), x holds this device's frames and the state is
sequence-wide on every device. What a layer exchanges: dense, every device's K and V
around the ring (`ring_attention`); K/V downsampling, the kept tokens' rows (one psum);
merging, the dst tokens' unit metric rows around the ring and every src's best score
(all-gather) when it matches, the float32 group sums of Q, K and V reduce-scattered block
by block (each device keeps its share of the merged rows), the merged K/V around the
ring, and the merged output rows around the ring for the unmerge. See docs/sharding.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops import chunks

from rvggt_jax.model import layers
from rvggt_jax.ops.attention import NEG_BIAS, attention, log_sizes, ring_attention
from rvggt_jax.ops.shards import FrameShards
from rvggt_jax.compression import kv as kv_lib
from rvggt_jax.compression import merge as merge_lib
from rvggt_jax.compression.config import CompressionConfig, LayerKind
from rvggt_jax.compression.kv import KVSlots
from rvggt_jax.compression.merge import Match
from rvggt_jax.compression.partition import Geometry, saliency_protect_count, stride_protected
from rvggt_jax.compression.plan import LayerPlan, layer_plan, padded_head_dim


class State(NamedTuple):
    """The per-forward compression state (see the module docstring)."""

    geometry: Geometry  # static: frames, grid, special tokens
    shards: FrameShards  # static: the frames of x on this device
    protected: jax.Array | None  # [B, N] bool, the Psi- (or stride-) protected tokens (None without protection)
    protected_pos: jax.Array | None  # [B, P] int32, their positions
    matches: dict[str, Match]  # the band-aligned match cache
    kv: dict[tuple[str, tuple[int, int]], KVSlots]  # the dynamic K/V slots of cached matches

    def with_match(self, key: str, match: Match) -> "State":
        return self._replace(matches={**self.matches, key: match})


def init_state(comp: CompressionConfig, saliency: jax.Array | None, geom: Geometry,
               shards: FrameShards | None = None) -> State:
    """Per-forward state: protection flags from the saliency Psi [B, S, h*w] of every frame
    (`shards`: the frames of this device, default all).

    Protected patches of a frame s >= 1: its top max(1, floor(alpha*T)) patches under Psi
    (`lax.top_k`); with `protect="stride"` a fixed stride over the sequence (FastVGGT)."""
    frames, L, N = geom.frames, geom.per_frame, geom.tokens
    shards = FrameShards.single(frames) if shards is None else shards
    protected = protected_pos = None
    if comp.protect == "saliency":
        per_frame = saliency_protect_count(geom, comp.alpha)
        if saliency is None:
            raise ValueError("saliency protection needs the saliency Psi [B, S, h*w]")
        b = saliency.shape[0]
        if saliency.shape != (b, frames, geom.patches):
            raise ValueError(f"saliency must be [B, {frames}, {geom.patches}]; got {saliency.shape}")
        if per_frame > 0 and frames > 1:
            _, top = jax.lax.top_k(saliency[:, 1:].astype(jnp.float32), per_frame)  # [B, S-1, per_frame]
            offsets = (jnp.arange(1, frames, dtype=jnp.int32) * L + geom.num_special)[None, :, None]
            protected_pos = (top.astype(jnp.int32) + offsets).reshape(b, -1)
            protected = jnp.zeros((b, N), bool).at[jnp.arange(b)[:, None], protected_pos].set(True)
    elif comp.protect == "stride":
        b = 1 if saliency is None else saliency.shape[0]
        pos = stride_protected(N, comp.alpha)
        flags = np.zeros(N, bool)
        flags[pos] = True
        protected_pos = jnp.broadcast_to(jnp.asarray(pos, jnp.int32), (b, pos.size))
        protected = jnp.broadcast_to(jnp.asarray(flags), (b, N))
    return State(geom, shards, protected, protected_pos, {}, {})


def dense_global_block(p_block, x: jax.Array, pos, config, shards: FrameShards | None = None,
                       per_frame: int = 0) -> jax.Array:
    """A dense global block over x [B, N, C]. Split over devices (`shards`: x holds this
    device's frames, `per_frame` tokens each), its queries attend to every device's keys,
    which travel around the devices (`ring_attention`); padding frames are masked."""
    heads, dtype = config.num_heads, config.compute_dtype
    if shards is None or not shards.sharded:
        return layers.block(p_block, x, heads, pos, config.rope_freq, dtype=dtype)
    b, n, c = x.shape
    if not isinstance(pos, layers.RopeTables):
        pos = layers.RopeTables.from_positions(pos, c // heads, config.rope_freq)
    q, k, v = layers.normed_qkv(p_block, x, heads, pos, dtype=dtype)
    mask = None
    if shards.padded > shards.frames:
        real = shards.offset(per_frame) + jnp.arange(n) < shards.frames * per_frame
        mask = jnp.broadcast_to(jnp.where(real, 0.0, NEG_BIAS).astype(jnp.float32), (b, n))
    out = ring_attention(q, k, v, mask, shards)
    # the block around the ring's output rows
    return layers.run_block(p_block, x, lambda xc, oc: oc, (out,), dtype=dtype)


def global_block(p_block, x: jax.Array, pos: jax.Array, layer: int, config, state: State
                 ) -> tuple[jax.Array, State]:
    """One global block under the configured compression.

    p_block: one upstream Block's params; x [B, N, C] (the float32 residual stream),
    N = S*P; pos: the sequence's RoPE tables [1, N, 1, D] (or integer positions
    [1, N, 2]); layer: the global layer index (Python int); config: the `VGGTConfig`
    (heads, RoPE, compute dtype, compression). Attention and MLP run in
    `config.compute_dtype`. Returns (x [B, N, C], state), the state with this layer's
    match (and K/V slots) cached when its plan stores them.
    """
    comp = config.compression
    geom, shards = state.geometry, state.shards
    plan = layer_plan(comp, layer, geom)
    L = geom.per_frame
    b, n, c = x.shape
    if n != shards.local * L:
        raise ValueError(f"global block {layer}: {n} tokens but the state describes {shards.local * L}")
    heads, freq, dtype = config.num_heads, config.rope_freq, config.compute_dtype
    d = c // heads

    if plan.kind == LayerKind.DENSE:
        return dense_global_block(p_block, x, pos, config, shards, L), state
    if plan.kind == LayerKind.FRAME:
        frame_pos = pos.first(L) if isinstance(pos, layers.RopeTables) else pos[:, :L]
        out = layers.block(p_block, x.reshape(b * shards.local, L, c), heads, frame_pos, freq, dtype=dtype)
        return out.reshape(b, n, c), state

    part = plan.partition
    if not isinstance(pos, layers.RopeTables):
        pos = layers.RopeTables.from_positions(pos, d, freq)
    protected = state.protected

    if plan.kind == LayerKind.KV:
        # K and V only of the kept tokens (projection, qk-norm and RoPE are per token, so
        # selecting before projecting is exact), then Q chunk by chunk, each chunk
        # attending and finishing its rows: no full-sequence Q, K or V.
        fixed = plan.fixed_kv
        sel = jnp.broadcast_to(jnp.asarray(fixed, jnp.int32), (b, fixed.size))
        log_g = None
        if plan.n_dyn:
            idx, ok = kv_lib.dynamic_slots(plan, comp, None, protected)
            sel = jnp.concatenate([sel, idx], axis=1)
            valid = jnp.concatenate([jnp.ones((b, fixed.size), bool), ok], axis=1)
            log_g = log_sizes(jnp.ones(valid.shape, jnp.float32), valid)
        kk, vv = _rows_kv(p_block, x, sel, pos, heads, dtype, shards, L)
        _check_shapes(plan, comp, n, kk, log_g)
        attend = layers.attention_to(p_block, heads, kk, vv, log_g, dtype=dtype)
        return layers.run_block(p_block, x, attend, (pos.cos, pos.sin), dtype=dtype), state

    # ---- merging layer -------------------------------------------------------------------
    def compute():
        # the norm1 metric is applied to the rows the matching gathers, never to all of x
        norm1 = None if plan.metric == "input" else (lambda rows: layers.layer_norm(p_block["norm1"], rows, dtype=dtype))
        protected_src = None if protected is None else jnp.take(protected, part.src_pos, axis=1, mode="clip")
        return merge_lib.compute_match(x, protected_src, plan, comp.match_chunk, dtype, norm1, shards)

    if plan.match == "reuse":
        if plan.match_key not in state.matches:
            raise ValueError(f"global block {layer} reuses the match of {plan.match_key}, which is not cached")
        match = state.matches[plan.match_key]
    else:
        match = compute()
        if plan.match_key is not None:
            state = state.with_match(plan.match_key, match)

    # Group means of q, k, v (after qk-norm and RoPE), summed chunk by chunk as they are
    # projected: no full-sequence Q, K or V. One pass each, so that one float32 sum
    # [B, N_m, C] exists at a time (the norm is recomputed, a small price).
    # Over devices, the merged rows are split in `rows` per device (a padding group at
    # N_m collects the padding frames' tokens); each device projects its own tokens and
    # the group sums are reduce-scattered one block at a time (`ring_sum_scatter`): no
    # device holds the sums of every group.
    sizes = match.sizes
    n_groups = plan.n_query + int(shards.padded > shards.frames)
    rows = shards.share(n_groups)
    group = shards.local_part(match.group, 1, L, pad_value=plan.n_query)
    first_row = shards.index() * rows
    sizes_own = jax.lax.dynamic_slice_in_dim(
        jnp.pad(sizes, ((0, 0), (0, rows * shards.devices - plan.n_query)), constant_values=1.0), first_row, rows, 1)

    def merged(parts, after=None):
        fn = layers.qkv_fn(p_block, heads, layers.TORCH_LN_EPS, dtype, parts)
        if not shards.sharded:
            # each sum made after the match, then after the previous mean; the loops own x
            # (see chunks.read_tokens)
            return merge_lib.merge_map(fn, (x, pos.cos, pos.sin), match, plan.n_query, bytes_per_row=c * 4 * 2,
                                       dep=match.group if after is None else after, owned=True)
        # one of q, k, v at a time: each projected after the previous one is summed; the
        # projecting loop owns x (chunks.read_tokens)
        xs, (vals,) = chunks.read_tokens(fn, x, (pos.cos, pos.sin), bytes_per_row=b * c * 4 * 2 + c * 4,
                                         dep=match.group if after is None else after)
        sums = shards.ring_sum_scatter(
            lambda block, acc: merge_lib.block_sums(vals, group - block * rows, rows, into=acc))
        return xs, (sums / sizes_own[..., None, None]).astype(vals.dtype)

    x, qm = merged("q")  # [B, rows, H, D]: this device's merged rows
    x, km = merged("k", qm)
    x, vm = merged("v", km)
    # Over devices, the keys are every device's merged rows, passed around (those the
    # layer does not keep masked out: each device holds two devices' rows at a time
    # instead of every kept row)
    ring = shards.sharded
    own_rows = first_row + jnp.arange(rows)

    if plan.kv_mode == "all":
        kk, vv, g, valid = km, vm, (sizes_own if ring else sizes), None
        if ring:
            valid = jnp.broadcast_to(own_rows < plan.n_query, (b, rows))
    else:
        fixed = plan.fixed_kv
        kv_key = None if plan.match_key is None else (plan.match_key, plan.tile)
        if kv_key is not None and kv_key in state.kv:
            idx, ok = state.kv[kv_key]
        else:
            idx, ok = slots = kv_lib.dynamic_slots(plan, comp, match, protected)
            if kv_key is not None:
                state = state._replace(kv={**state.kv, kv_key: slots})
        sel = jnp.concatenate([jnp.broadcast_to(jnp.asarray(fixed, jnp.int32), (b, fixed.size)), idx], axis=1)
        valid = jnp.concatenate([jnp.ones((b, fixed.size), bool), ok], axis=1)
        if ring:  # this device's merged rows, the kept ones marked (the slots are distinct rows)
            rel = sel - first_row  # (negative ones would wrap around in a scatter)
            rel = jnp.where(valid & (rel >= 0) & (rel < rows), rel, rows)
            valid = jnp.zeros((b, rows), bool).at[jnp.arange(b)[:, None], rel].set(True, mode="drop")
            kk, vv, g = km, vm, sizes_own
        else:
            kk, vv = chunks.take_along(km, sel, axis=1), chunks.take_along(vm, sel, axis=1)
            g = jnp.take_along_axis(sizes, sel, axis=1, mode="promise_in_bounds")

    dup = None
    if plan.n_dup:
        # The authors' artefact: the protected dst tokens once more, un-merged, size 1.
        protected_pos = state.protected_pos
        dk, dv = _rows_kv(p_block, x, protected_pos, pos, heads, dtype, shards, L)
        # only protected dst come twice: the authors drop protected src from both lists
        dup_ok = jnp.take(jnp.asarray(part.is_dst), protected_pos, mode="clip")
        if plan.kv_mode == "select" and not (comp.kv_protect_saliency and comp.protect == "saliency"):
            dup_ok = dup_ok & jnp.take(jnp.asarray(plan.kv_keep), protected_pos, mode="clip")
        dup = (dk, dv, jnp.ones(protected_pos.shape, jnp.float32), dup_ok)
        if not ring:
            kk = jnp.concatenate([kk, dk], axis=1)
            vv = jnp.concatenate([vv, dv], axis=1)
            g = jnp.concatenate([g, dup[2]], axis=1)
            if valid is None:
                valid = jnp.ones(g.shape[:1] + (g.shape[1] - protected_pos.shape[1],), bool)
            valid = jnp.concatenate([valid, dup_ok], axis=1)

    def bias(g, valid, masked):
        if not plan.size_column and not masked:
            return None
        return log_sizes(g if comp.size_bias and plan.size_column else jnp.ones_like(g), valid if masked else None)

    if ring:
        # (the padding rows are always masked; log 1 = 0 keeps a layer without the size
        # column exact)
        extra = () if dup is None else ((dup[0], dup[1], bias(dup[2], dup[3], plan.masked)),)
        log_g = bias(g, valid, True)
        # Q and K wait for V's sums: else XLA transposes and blocks them early, and they sit
        # through V's sums (0.27 GB per device at 1000 frames of VGGT-1B in bfloat16 over 8
        # devices)
        out = ring_attention(chunks.after(qm, vm), chunks.after(kk, vm), vv, log_g, shards, extra)
    else:
        log_g = bias(g, valid, plan.masked) if plan.size_column else None
        _check_shapes(plan, comp, qm.shape[1], kk, log_g)
        out = attention(qm, kk, vv, log_g)
    # the output projection on the merged rows, then every token takes its group's row
    proj = p_block["attn"]["proj"]
    out = chunks.map_tokens(lambda oc: layers.linear(proj, oc), (out.reshape(b, rows, c),),
                            bytes_per_row=b * c * 4 * 4)
    # (the block's attention hook: merge -> attend -> project happened above, on the merged
    # rows; the hook unmerges, each token taking its group's row)
    if not shards.sharded:
        x = layers.run_block(p_block, x, lambda xc, gc: merge_lib.unmerge(out, gc), (group,), dtype=dtype,
                             projected=True)
    else:  # the merged rows travel around the devices, each token taking its group's
        x = layers.run_block(p_block, x, lambda xc, rc: rc, (shards.ring_take(out, group),), dtype=dtype,
                             projected=True)
    return x, state


def _check_shapes(plan: LayerPlan, comp: CompressionConfig, queries: int, keys: jax.Array, log_g) -> None:
    """At trace time: the attention's queries, K/V slots and folded head dimension are the
    plan's (what the cost model reads)."""
    d = keys.shape[-1]
    want = (plan.n_query, plan.n_kv, padded_head_dim(d, plan.size_column, comp.head_pad_multiple))
    got = (queries, keys.shape[1], padded_head_dim(d, log_g is not None, comp.head_pad_multiple))
    if got != want:
        raise AssertionError(f"global block {plan.layer}: (queries, K/V slots, head dim) {got} but the plan "
                             f"says {want}")


def _rows_kv(p_block, x: jax.Array, idx: jax.Array, pos: layers.RopeTables, heads: int, dtype,
             shards: FrameShards, per_frame: int) -> tuple[jax.Array, jax.Array]:
    """K and V [B, M, H, d] of the tokens idx [B, M] (global positions) of the sequence
    whose rows x [B, N, C] this device holds (their norm1, projection, qk-norm and RoPE
    at their own positions; `pos` the tables of x's tokens, which repeat every frame)."""
    rows = shards.take_rows(x, idx, per_frame)
    local = idx % per_frame
    tables = pos.frame_rows(local)
    return layers.normed_qkv(p_block, rows, heads, tables, dtype=dtype, parts="kv")
