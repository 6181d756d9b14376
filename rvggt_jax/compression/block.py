"""The compressed global block and its per-forward state.

    state = init_state(config, saliency, frames, grid_hw)      # once per forward
    x, state = global_block(p_block, x, pos, layer, config, state)

`layer` is a Python int and the aggregator loops over layers in Python, so every layer
has its own static plan (`plan.layer_plan`) and the state may gain entries (the band
caches) from one layer to the next. Nothing branches on data: every shape comes from
(x.shape, grid, configuration).

The state is a dict:
  geometry   static `Geometry` (frames, grid, special tokens; a static pytree node)
  protected  [B, N] bool, the Psi- (or stride-) protected tokens (absent without protection)
  protected_pos [B, P] int32, their positions (saliency protection)
  match      {cache key: match} (see merge.py), the band-aligned match cache
  kv         {cache key + K/V rule: (idx, valid)}, the dynamic K/V slots of cached matches
  shards     static `FrameShards`: the frames of x on this device (absent: all of them)

Split over devices (`FrameShards`), x holds this device's frames and the state is
sequence-wide on every device. What a layer exchanges: dense, every device's K and V
around the ring (`ring_attention`); K/V downsampling, the kept tokens' rows (one psum);
merging, the dst tokens' unit metric rows around the ring and every src's best score
(all-gather) when it matches, the float32 group sums of Q, K and V reduce-scattered block
by block (each device keeps its share of the merged rows), the merged K/V around the
ring, and the merged output rows around the ring for the unmerge. See docs/sharding.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax import chunks, layers
from rvggt_jax.attention import NEG_BIAS, attention, log_sizes, ring_attention
from rvggt_jax.frames import FrameShards
from rvggt_jax.compression import kv as kv_lib
from rvggt_jax.compression import merge as merge_lib
from rvggt_jax.compression.partition import kv_static_keep, partition, saliency_protect_count, stride_protected
from rvggt_jax.compression.plan import LayerPlan, fixed_kv_index, layer_plan, padded_head_dim

State = dict[str, Any]

# Trace-time record of the shapes the block really uses (see `record_shapes`).
_SHAPE_LOG: list[dict[str, Any]] | None = None


class record_shapes:
    """Context manager collecting, at trace time, one dict per compressed global block:
    layer, kind, queries, kv slots, the folded head dim. Used by the cost-model tests."""

    def __enter__(self):
        global _SHAPE_LOG
        self._prev, _SHAPE_LOG = _SHAPE_LOG, []
        return _SHAPE_LOG

    def __exit__(self, *exc):
        global _SHAPE_LOG
        _SHAPE_LOG = self._prev
        return False


def _log(**kw):
    if _SHAPE_LOG is not None:
        _SHAPE_LOG.append(kw)


@dataclass(frozen=True)
class Geometry:
    frames: int
    h: int
    w: int
    num_special: int

    @property
    def per_frame(self) -> int:
        return self.num_special + self.h * self.w


jax.tree_util.register_static(Geometry)


def init_state(config, saliency: jax.Array | None, frames: int, grid_hw: tuple[int, int]) -> State:
    """Per-forward state: protection flags from the saliency Psi [B, S, h*w].

    Protected patches of a frame s >= 1: its top max(1, floor(alpha*T)) patches under Psi
    (`lax.top_k`); with `protect="stride"` a fixed stride over the sequence (FastVGGT)."""
    cc = config.compression
    h, w = grid_hw
    ns = config.patch_start_idx
    geom = Geometry(frames, h, w, ns)
    L = geom.per_frame
    N = frames * L
    state: State = {"geometry": geom, "match": {}, "kv": {}}
    if cc.protect == "saliency":
        kp = saliency_protect_count(h, w, cc.alpha)
        if saliency is None:
            raise ValueError("saliency protection needs the saliency Psi [B, S, h*w]")
        b = saliency.shape[0]
        if saliency.shape != (b, frames, h * w):
            raise ValueError(f"saliency must be [B, {frames}, {h * w}]; got {saliency.shape}")
        if kp > 0 and frames > 1:
            _, top = jax.lax.top_k(saliency[:, 1:].astype(jnp.float32), kp)  # [B, S-1, kp]
            offsets = (jnp.arange(1, frames, dtype=jnp.int32) * L + ns)[None, :, None]
            pos = (top.astype(jnp.int32) + offsets).reshape(b, -1)
            flags = jnp.zeros((b, N), bool).at[jnp.arange(b)[:, None], pos].set(True)
            state["protected_pos"] = pos
            state["protected"] = flags
    elif cc.protect == "stride":
        b = 1 if saliency is None else saliency.shape[0]
        pos = stride_protected(N, cc.alpha)
        flags = np.zeros(N, bool)
        flags[pos] = True
        state["protected_pos"] = jnp.broadcast_to(jnp.asarray(pos, jnp.int32), (b, pos.size))
        state["protected"] = jnp.broadcast_to(jnp.asarray(flags), (b, N))
    return state


def empty_match(plan: LayerPlan, batch: int) -> dict[str, jax.Array]:
    """A match of the plan's shapes filled with zeros (the initial carry of a band's scan)."""
    return {"group": jnp.zeros((batch, plan.tokens), jnp.int32),
            "sizes": jnp.zeros((batch, plan.n_query), jnp.float32),
            "unm_pos": jnp.zeros((batch, plan.n_unm), jnp.int32)}


def plan_for(config, layer: int, geom: Geometry) -> LayerPlan:
    return layer_plan(config.compression, layer, geom.frames, geom.h, geom.w, geom.num_special)


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
    proj = p_block["attn"]["proj"]
    return layers.finish_block(p_block, x, lambda oc: layers.linear(proj, oc.reshape(oc.shape[:2] + (c,))), (out,),
                               dtype=dtype)


def global_block(p_block, x: jax.Array, pos: jax.Array, layer: int, config, state: State
                 ) -> tuple[jax.Array, State]:
    """One global block under the configured compression.

    p_block: one upstream Block's params; x [B, N, C] (the float32 residual stream),
    N = S*P; pos: the sequence's RoPE tables [1, N, 1, D] (or integer positions
    [1, N, 2]); layer: the global layer index (Python int). Attention and MLP run in
    `config.compute_dtype`. Returns (x [B, N, C], state), the state with this layer's
    match (and K/V slots) cached when its plan stores them.
    """
    cc = config.compression
    geom: Geometry = state["geometry"]
    plan = plan_for(config, layer, geom)
    shards = state.get("shards") or FrameShards.single(geom.frames)
    L = geom.per_frame
    b, n, c = x.shape
    if n != shards.local * L:
        raise ValueError(f"global block {layer}: {n} tokens but the state describes {shards.local * L}")
    heads, freq, dtype = config.num_heads, config.rope_freq, config.compute_dtype
    d = c // heads

    if plan.kind == "dense":
        _log(layer=layer, kind="dense", queries=n, kv=n, head_dim=d)
        return dense_global_block(p_block, x, pos, config, shards, L), state
    if plan.kind == "frame":
        _log(layer=layer, kind="frame", queries=L, kv=L, head_dim=d)
        out = layers.block(p_block, x.reshape(b * shards.local, L, c), heads, pos[:, :L], freq, dtype=dtype)
        return out.reshape(b, n, c), state

    state = dict(state)
    part = partition(geom.frames, geom.h, geom.w, geom.num_special, cc.dst_seed)
    if not isinstance(pos, layers.RopeTables):
        pos = layers.RopeTables.from_positions(pos, d, freq)
    protected = state.get("protected")

    if plan.kind == "kv":
        # K and V only of the kept tokens (projection, qk-norm and RoPE are per token, so
        # selecting before projecting is exact), then Q chunk by chunk, each chunk
        # attending and finishing its rows: no full-sequence Q, K or V.
        fixed = fixed_kv_index(cc, layer, geom.frames, geom.h, geom.w, geom.num_special)
        sel = jnp.broadcast_to(jnp.asarray(fixed, jnp.int32), (b, fixed.size))
        log_g = None
        if plan.n_dyn:
            idx, ok = kv_lib.dynamic_slots(plan, part, cc, None, protected, geom.num_special, geom.h, geom.w)
            sel = jnp.concatenate([sel, idx], axis=1)
            valid = jnp.concatenate([jnp.ones((b, fixed.size), bool), ok], axis=1)
            log_g = log_sizes(jnp.ones(valid.shape, jnp.float32), valid)
        kk, vv = _rows_kv(p_block, x, sel, pos, heads, dtype, shards, L)
        _log(layer=layer, kind="kv", queries=n, kv=kk.shape[1], head_dim=_folded_dim(d, log_g, cc))
        return layers.attend_rows(p_block, x, (pos.cos, pos.sin), kk, vv, heads, log_g, dtype=dtype), state

    # ---- merging layer -------------------------------------------------------------------
    def compute():
        # the norm1 metric is applied to the rows the matching gathers, never to all of x
        norm1 = None if plan.metric == "input" else (lambda rows: layers.layer_norm(p_block["norm1"], rows, dtype=dtype))
        prot_src = None if protected is None else jnp.take(protected, part.src_pos, axis=1, mode="clip")
        return merge_lib.compute_match(x, prot_src, part, plan, cc.match_chunk, dtype, norm1, shards, L)

    if plan.match == "reuse":
        if plan.match_key not in state["match"]:
            raise ValueError(f"global block {layer} reuses the match of {plan.match_key}, which is not cached")
        match = state["match"][plan.match_key]
    else:
        match = compute()
        if plan.match_key is not None:
            state["match"] = {**state["match"], plan.match_key: match}

    # Group means of q, k, v (after qk-norm and RoPE), summed chunk by chunk as they are
    # projected: no full-sequence Q, K or V. One pass each, so that one float32 sum
    # [B, N_m, C] exists at a time (the norm is recomputed, a small price).
    # Over devices, the merged rows are split in `rows` per device (a padding group at
    # N_m collects the padding frames' tokens); each device projects its own tokens and
    # the group sums are reduce-scattered one block at a time (`ring_sum_scatter`): no
    # device holds the sums of every group.
    sizes = match["sizes"]
    n_groups = plan.n_query + int(shards.padded > shards.frames)
    rows = shards.share(n_groups)
    group = shards.local_part(match["group"], 1, L, pad_value=plan.n_query)
    first_row = shards.index() * rows
    sizes_own = jax.lax.dynamic_slice_in_dim(
        jnp.pad(sizes, ((0, 0), (0, rows * shards.devices - plan.n_query)), constant_values=1.0), first_row, rows, 1)

    def merged(part, after=None):
        fn = layers.qkv_fn(p_block, heads, layers.TORCH_LN_EPS, dtype, part)
        if not shards.sharded:
            # each sum made after the previous mean; the loops own x (see chunks.read_tokens)
            xo, mean = merge_lib.merge_map(fn, (x, pos.cos, pos.sin), match, plan.n_query, bytes_per_row=c * 4 * 2,
                                           dep=after, owned=True)
            return xo, mean
        # one of q, k, v at a time: each projected after the previous one is summed
        xs = x if after is None else jax.lax.optimization_barrier((x, after))[0]
        vals = chunks.map_tokens(fn, (xs, pos.cos, pos.sin), bytes_per_row=b * c * 4 * 2 + c * 4,
                                 dep=xs if after is None else after)[0]
        sums = shards.ring_sum_scatter(lambda block: merge_lib.block_sums(vals, group - block * rows, rows))
        return (sums / sizes_own[..., None, None]).astype(vals.dtype)

    if shards.sharded:
        qm = merged("q")  # [B, rows, H, D]: this device's merged rows
        km = merged("k", qm)
        vm = merged("v", km)
    else:
        x, qm = merged("q", match["group"])
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
        fixed = fixed_kv_index(cc, layer, geom.frames, geom.h, geom.w, geom.num_special)
        kv_key = None if plan.match_key is None else f"{plan.match_key}|{plan.tile}"
        if kv_key is not None and kv_key in state["kv"]:
            idx, ok = state["kv"][kv_key]
        else:
            idx, ok = kv_lib.dynamic_slots(plan, part, cc, match, protected, geom.num_special, geom.h, geom.w)
            if kv_key is not None:
                state["kv"] = {**state["kv"], kv_key: (idx, ok)}
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
        ppos = state["protected_pos"]
        dk, dv = _rows_kv(p_block, x, ppos, pos, heads, dtype, shards, L)
        # only protected dst come twice: the authors drop protected src from both lists
        dup_ok = jnp.take(jnp.asarray(part.is_dst), ppos, mode="clip")
        if plan.kv_mode == "select" and not (cc.kv_protect_saliency and cc.protect == "saliency"):
            keep = jnp.asarray(kv_static_keep(geom.frames, geom.h, geom.w, geom.num_special, plan.tile,
                                              cc.phase_shift, cc.anchor))
            dup_ok = dup_ok & jnp.take(keep, ppos, mode="clip")
        dup = (dk, dv, jnp.ones(ppos.shape, jnp.float32), dup_ok)
        if not ring:
            kk = jnp.concatenate([kk, dk], axis=1)
            vv = jnp.concatenate([vv, dv], axis=1)
            g = jnp.concatenate([g, dup[2]], axis=1)
            if valid is None:
                valid = jnp.ones(g.shape[:1] + (g.shape[1] - ppos.shape[1],), bool)
            valid = jnp.concatenate([valid, dup_ok], axis=1)

    def bias(g, valid, masked):
        if not plan.size_column and not masked:
            return None
        return log_sizes(g if cc.size_bias and plan.size_column else jnp.ones_like(g), valid if masked else None)

    if ring:
        # (the padding rows are always masked; log 1 = 0 keeps a layer without the size
        # column exact)
        extra = () if dup is None else ((dup[0], dup[1], bias(dup[2], dup[3], plan.masked)),)
        log_g = bias(g, valid, True)
        out = ring_attention(qm, kk, vv, log_g, shards, extra)
    else:
        log_g = bias(g, valid, plan.masked) if plan.size_column else None
        out = attention(qm, kk, vv, log_g)
    _log(layer=layer, kind="merge", queries=qm.shape[1], kv=kk.shape[1], head_dim=_folded_dim(d, log_g, cc))
    # the output projection on the merged rows, then every token takes its group's row
    proj = p_block["attn"]["proj"]
    out = chunks.map_tokens(lambda oc: layers.linear(proj, oc), (out.reshape(b, rows, c),),
                            bytes_per_row=b * c * 4 * 4)
    if not shards.sharded:
        x = layers.finish_block(p_block, x, lambda gc: merge_lib.unmerge(out, {"group": gc}), (group,), dtype=dtype)
    else:  # the merged rows travel around the devices, each token taking its group's
        x = layers.finish_block(p_block, x, lambda rc: rc, (shards.ring_take(out, group),), dtype=dtype)
    return x, state


def _rows_kv(p_block, x: jax.Array, idx: jax.Array, pos: layers.RopeTables, heads: int, dtype,
             shards: FrameShards, per_frame: int) -> tuple[jax.Array, jax.Array]:
    """K and V [B, M, H, d] of the tokens idx [B, M] (global positions) of the sequence
    whose rows x [B, N, C] this device holds (their norm1, projection, qk-norm and RoPE
    at their own positions; `pos` the tables of x's tokens, which repeat every frame)."""
    rows = shards.take_rows(x, idx, per_frame)
    local = idx % per_frame
    tables = layers.RopeTables(*(jnp.take(t[0], local, axis=0, mode="clip") for t in (pos.cos, pos.sin)))
    return layers.normed_qkv(p_block, rows, heads, tables, dtype=dtype, parts="kv")


def _folded_dim(d: int, log_g, cc) -> int:
    return padded_head_dim(d, log_g is not None, cc.head_pad_multiple)
