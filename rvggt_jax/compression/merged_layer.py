"""A merging global block: match -> merged Q/K/V -> attention over the merged rows ->
output projection -> unmerge, every token taking its group's row.

    x, state = merging_block(p_block, x, pos, plan, config, state)

The steps, each a function below: the layer's `Match` (computed, or reused from the
band's cache); the merged rows kept as keys (`key_slots`); then, for one group of heads
after another (`head_groups`, `CompressionConfig.merge_head_groups`), the group means of
q, k and v (`merged_qkv`: summed chunk by chunk as they are projected, no full-sequence
Q, K or V), the keys (`kept_keys`: all merged rows, or the K/V-downsampled slots, plus
the authors' duplicated protected dst) and the attention (`attend`: one device, or
around the ring; on one device with the dynamic slots a sequence typically fills,
`within_capacity`); the unmerge inside the block. With `duplicate_protected`, the
protected tokens' own (un-merged) queries attend too, and each protected dst token takes
its own row, as the authors' unmerge gives it (`protected_queries`, `own_rows`): in
`n_dup` rows after the merged ones, or, when the plan says `protected_rows`, in the U
unmerged rows, which are then the protected tokens' own (`own_qkv`). Heads
attend independently, so the groups change no value; they bound the float32 sums and
merged rows alive at once.

Split over devices, the merged rows are split in `rows` per device (a padding group at
N_m collects the padding frames' tokens): each device projects its own tokens, the group
sums are reduce-scattered one block at a time, the merged K/V and the merged output rows
travel around the ring. See docs/sharding.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from rvggt_jax.compression import kv as kv_lib
from rvggt_jax.compression import merge as merge_lib
from rvggt_jax.compression.merge import Match
from rvggt_jax.compression.kv_layer import rows_kv
from rvggt_jax.compression.plan import LayerPlan, check_shapes
from rvggt_jax.compression.state import State
from rvggt_jax.model import layers
from rvggt_jax.model.params import Params
from rvggt_jax.ops import chunks
from rvggt_jax.ops.attention import attention, log_sizes
from rvggt_jax.ops.ordering import ordered_after, zeros_after
from rvggt_jax.ops.ring import ring_attention
from rvggt_jax.ops.shards import frame_layout


class MergedRows(NamedTuple):
    """This device's share of the merged rows (all of them on one device)."""

    rows: int  # merged rows per device
    first: jax.Array | int  # the index of this device's first merged row
    group: jax.Array  # [B, N] int32: the group of each of this device's tokens
    sizes: jax.Array  # [B, rows] float32: the group sizes of this device's rows


class Keys(NamedTuple):
    """The keys a merging layer attends to."""

    k: jax.Array  # [B, M, H, D]
    v: jax.Array  # [B, M, H, D]
    sizes: jax.Array  # [B, M] group sizes g (the size bias log g)
    valid: jax.Array | None  # [B, M] bool, or None when every slot is a key
    dup: tuple | None  # over devices: (k, v, sizes, valid) of the duplicated protected dst


def merging_block(p_block: Params, x: jax.Array, pos: layers.RopeTables, plan: LayerPlan, config, state: State
                  ) -> tuple[jax.Array, State]:
    """One merging global block over x [B, N, C] (this device's frames; pos: their RoPE
    tables) under `plan` -> (x [B, N, C], the state with this layer's match and K/V slots
    cached when the plan stores them). The means, keys and attention run for one group
    of heads after another (`head_groups`), each group's sums made after the previous
    group's output."""
    match, state = layer_match(p_block, x, plan, config, state)
    share = merged_rows(match, plan)
    slots, state = key_slots(plan, config, match, state)
    b, c = x.shape[0], x.shape[-1]
    groups = head_groups(config.num_heads, config.compression.merge_head_groups)
    rows = share.rows + plan.n_dup_all  # the merged rows, then the protected tokens' own rows

    def group_attention(x, p_heads, heads, after):
        """(x, attention output [B, rows, heads, D]) of one group of heads."""
        x, qm, km, vm = merged_qkv(p_heads, x, pos, match, share, plan, config, heads, after)
        if plan.protected_rows:
            qm, km, vm = own_qkv(p_heads, x, pos, (qm, km, vm), share, plan, config, state, heads)

        def attend_slots(slots, dyn):
            keys = kept_keys(p_heads, x, pos, km, vm, match, share, plan, config, state, slots, heads)
            if plan.n_dup_all:
                q = jnp.concatenate([qm, protected_queries(p_heads, x, pos, plan, config, state, heads)], axis=1)
                return attend_duplicates(q, keys, plan, config, state, dyn)
            return attend(qm, keys, plan, config, dyn=dyn)

        return x, within_capacity(attend_slots, slots, plan)

    if len(groups) == 1:
        x, out = group_attention(x, p_block, config.num_heads, match.group)
    elif len({len(g) for g in groups}) == 1:
        # equal groups: one loop, one compiled copy of the group's code (an unrolled loop
        # would compile the means, keys and attention once per group)
        heads = len(groups[0])
        out = zeros_after((b, rows, config.num_heads, config.head_dim), config.compute_dtype, match.sizes)

        def step(g, carry):
            x, out = carry
            # the group's sums are made after the previous group's output (the carry)
            x, o = group_attention(x, heads_at(p_block, g * heads, heads, config.head_dim), heads, out)
            return x, jax.lax.dynamic_update_slice_in_dim(out, o.astype(out.dtype), g * heads, 2)

        x, out = jax.lax.fori_loop(0, len(groups), step, (x, out))
    else:
        outs, after = [], match.group
        for g in groups:
            x, o = group_attention(x, heads_at(p_block, g.start, len(g), config.head_dim), len(g), after)
            outs.append(o)
            after = o
        out = jnp.concatenate(outs, axis=2)  # [B, rows, H, D]
    # the output projection on the merged rows, then every token takes its group's row
    proj = p_block["attn"]["proj"]
    out = chunks.map_tokens(lambda oc: layers.linear(proj, oc), (out.reshape(b, rows, c),),
                            bytes_per_row=b * c * 4 * 4)
    own = own_rows(plan, x, state)
    if plan.protected_rows:  # a protected dst takes its own row among the U rows
        share, own = share._replace(group=jnp.where(own >= 0, plan.n_dst + own, share.group)), None
    return unmerge_block(p_block, x, out, share, plan, config, own), state


def head_groups(num_heads: int, groups: int) -> tuple[range, ...]:
    """The heads split into min(groups, num_heads) contiguous groups of near-equal size."""
    groups = min(groups, num_heads)
    edges = [(num_heads * g) // groups for g in range(groups + 1)]
    return tuple(range(a, b) for a, b in zip(edges[:-1], edges[1:]))


def heads_at(p_block: Params, first, count: int, head_dim: int) -> Params:
    """The block's parameters with its q, k, v projections cut to the `count` heads from
    `first` (static or traced): their output columns, a head group's projections. The
    norms (shared by the heads) and the output projection stay whole."""
    attn = p_block["attn"]

    def cut(lin):
        return {name: (jax.lax.dynamic_slice_in_dim(w, first * head_dim, count * head_dim, w.ndim - 1)
                       if name in ("kernel", "bias") else w) for name, w in lin.items()}

    return {**p_block, "attn": {**attn, **{name: cut(attn[name]) for name in "qkv"}}}


def layer_match(p_block: Params, x: jax.Array, plan: LayerPlan, config, state: State) -> tuple[Match, State]:
    """The layer's match: computed from x (cosine similarity of the metric, the protected
    src kept out) and cached when the plan stores it, or the band's cached one."""
    if plan.match == "reuse":
        if plan.match_key not in state.matches:
            raise ValueError(f"global block {plan.layer} reuses the match of {plan.match_key}, which is not cached")
        return state.matches[plan.match_key], state
    dtype = config.compute_dtype
    # the norm1 metric is applied to the rows the matching gathers, never to all of x
    norm1 = None if plan.metric == "input" else (lambda rows: layers.layer_norm(p_block["norm1"], rows, dtype=dtype))
    protected = state.protected
    protected_src = None if protected is None else jnp.take(protected, plan.partition.src_pos, axis=1, mode="clip")
    match = merge_lib.compute_match(x, protected_src, plan, config.compression.match_chunk, dtype, norm1,
                                    state.protected_pos)
    if plan.match_key is not None:
        state = state.with_match(plan.match_key, match)
    return match, state


def merged_rows(match: Match, plan: LayerPlan) -> MergedRows:
    """This device's share of the match's merged rows."""
    layout = frame_layout(frames=plan.frames)
    n_groups = plan.n_query + int(layout.padded > layout.frames)
    rows = layout.share(n_groups)
    group = layout.local_part(match.group, 1, plan.per_frame, pad_value=plan.n_query)
    first = layout.index() * rows
    padded = jnp.pad(match.sizes, ((0, 0), (0, rows * layout.devices - plan.n_query)), constant_values=1.0)
    return MergedRows(rows, first, group, jax.lax.dynamic_slice_in_dim(padded, first, rows, 1))


def merged_qkv(p_block: Params, x: jax.Array, pos: layers.RopeTables, match: Match, share: MergedRows,
               plan: LayerPlan, config, heads: int, after: jax.Array):
    """(x, q, k, v): the group means [B, rows, heads, D] of q, k and v (after qk-norm and
    RoPE) of this device's merged rows, for the heads p_block's projections make, x
    passing through the loops; the float32 sums made after `after`. On one device q, k
    and v are summed in one pass over the tokens (three sums of a head group at once:
    the head groups bound them); over devices one of q, k, v at a time, each after the
    previous mean (each is projected for all of the device's tokens before its sums are
    reduce-scattered)."""
    b, c = x.shape[0], x.shape[-1]
    dtype = config.compute_dtype
    layout = frame_layout(frames=plan.frames)

    def rows(parts):
        return layers.block_qkv_rows(p_block, heads, layers.TORCH_LN_EPS, dtype, parts)

    if not layout.sharded:
        return merge_lib.merge_map(rows("qkv"), (x, pos.cos, pos.sin), match, plan.n_query,
                                   bytes_per_row=c * 4 * 2 + 3 * c * 4, dep=after, owned=True)

    def means(x, parts, after):
        # each device projects its tokens, the group sums reduce-scattered
        xs, (vals,) = chunks.map_tokens_through(rows(parts), x, (pos.cos, pos.sin),
                                                bytes_per_row=b * c * 4 * 2 + c * 4, dep=after)
        sums = layout.ring_sum_scatter(
            lambda block, acc: merge_lib.block_sums(vals, share.group - block * share.rows, share.rows, into=acc))
        sizes = merge_lib.mean_divisor(share.sizes)[..., None, None]
        return xs, merge_lib.materialized((sums / sizes).astype(vals.dtype))

    x, qm = means(x, "q", after)  # [B, rows, heads, D]: this device's merged rows
    x, km = means(x, "k", qm)
    x, vm = means(x, "v", km)
    return x, qm, km, vm


def key_slots(plan: LayerPlan, config, match: Match, state: State) -> tuple[tuple | None, State]:
    """The merged rows a `kv_mode` "select" layer keeps as keys: (sel [B, M] row indices,
    valid [B, M]) = the fixed slots then the dynamic ones (cached per band and tile), or
    None when every merged row is a key; once per layer, whatever the head groups."""
    if plan.kv_mode == "all":
        return None, state
    b = match.group.shape[0]
    fixed = plan.fixed_kv
    kv_key = None if plan.match_key is None else (plan.match_key, plan.tile)
    if kv_key is not None and kv_key in state.kv:
        idx, ok = state.kv[kv_key]
    else:
        idx, ok = slots = kv_lib.dynamic_slots(plan, config.compression, match, state.protected)
        if kv_key is not None:
            state = state._replace(kv={**state.kv, kv_key: slots})
    sel = jnp.concatenate([jnp.broadcast_to(jnp.asarray(fixed, jnp.int32), (b, fixed.size)), idx], axis=1)
    valid = jnp.concatenate([jnp.ones((b, fixed.size), bool), ok], axis=1)
    return (sel, valid), state


def within_capacity(attend_slots, slots: tuple | None, plan: LayerPlan) -> jax.Array:
    """`attend_slots(slots, dyn)` with the layer's first `n_dyn_cap` dynamic K/V slots
    when this data fills no more of them (compacted: the filled ones come first), else
    with all `n_dyn` (`lax.cond`): the slots left out are empty, so both branches give
    the same values, and the short one attends with the slots a sequence typically fills.
    Every slot on a layer without dynamic slots, and over devices (the ring's keys are
    each device's merged rows)."""
    if slots is None or frame_layout(frames=plan.frames).sharded or plan.n_dyn_cap >= plan.n_dyn:
        return attend_slots(slots, plan.n_dyn)
    sel, valid = slots
    m = plan.n_fixed + plan.n_dyn_cap
    return jax.lax.cond(jnp.any(valid[:, m]), lambda: attend_slots(slots, plan.n_dyn),
                        lambda: attend_slots((sel[:, :m], valid[:, :m]), plan.n_dyn_cap))


def kept_keys(p_block: Params, x: jax.Array, pos: layers.RopeTables, km: jax.Array, vm: jax.Array, match: Match,
              share: MergedRows, plan: LayerPlan, config, state: State, slots: tuple | None, heads: int) -> Keys:
    """The keys of the layer for the heads of km, vm [B, rows, heads, D]: every merged row
    (`kv_mode` "all") or the kept slots (`key_slots`), and with `n_dup_all` the protected
    dst once more, un-merged, size 1 (the authors' artefact; `n_dup_all` slots, dst first,
    those of protected src masked). Over devices, the keys are
    this device's merged rows, those the layer does not keep masked out."""
    comp = config.compression
    ring = state.layout.sharded
    b = km.shape[0]
    own_rows = share.first + jnp.arange(share.rows)
    if slots is None:
        kk, vv, g, valid = km, vm, (share.sizes if ring else match.sizes), None
        if ring:
            valid = jnp.broadcast_to(own_rows < plan.n_query, (b, share.rows))
        if plan.r_max > plan.r:  # rows emptied by merges beyond the static r are no keys
            valid = g > 0 if valid is None else valid & (g > 0)
    else:
        sel, valid = slots
        if ring:  # this device's merged rows, the kept ones marked (the slots are distinct rows)
            rel = sel - share.first  # (negative ones would wrap around in a scatter)
            rel = jnp.where(valid & (rel >= 0) & (rel < share.rows), rel, share.rows)
            valid = jnp.zeros((b, share.rows), bool).at[jnp.arange(b)[:, None], rel].set(True, mode="drop")
            kk, vv, g = km, vm, share.sizes
        else:
            kk, vv = chunks.take_along(km, sel, axis=1), chunks.take_along(vm, sel, axis=1)
            g = jnp.take_along_axis(match.sizes, sel, axis=1, mode="promise_in_bounds")

    dup = None
    if plan.n_dup_all:
        protected_pos = state.protected_pos
        dk, dv = rows_kv(p_block, x, protected_pos, pos, config, plan, heads)
        # only protected dst come twice: the authors drop protected src from both lists
        dup_ok = jnp.take(jnp.asarray(plan.partition.is_dst), protected_pos, mode="clip")
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
            dup = None
    return Keys(kk, vv, g, valid, dup)


def own_qkv(p_block: Params, x: jax.Array, pos: layers.RopeTables, merged: tuple, share: MergedRows,
            plan: LayerPlan, config, state: State, heads: int) -> tuple[jax.Array, ...]:
    """`protected_rows`: the merged q, k, v [B, rows, heads, D] of this device's share with
    the U rows (N_dst + j) set to protected token j's own q, k, v (norm1, projection,
    qk-norm and RoPE of its row alone). A protected src's row is its own mean already;
    a protected dst's row has no member (it stays in its dst group) until written here."""
    idx = state.protected_pos  # [B, U]
    rows = state.layout.take_rows(x, idx, plan.per_frame)
    own = layers.block_qkv(p_block, rows, heads, pos.frame_rows(idx % plan.per_frame), dtype=config.compute_dtype)
    b, u = idx.shape
    rel = plan.n_dst + jnp.arange(u, dtype=jnp.int32) - share.first  # their rows in this device's share
    rel = jnp.where((rel >= 0) & (rel < share.rows), rel, share.rows)  # (outside: dropped)
    return tuple(m.at[:, rel].set(o.astype(m.dtype), mode="drop") for m, o in zip(merged, own))


def protected_queries(p_block: Params, x: jax.Array, pos: layers.RopeTables, plan: LayerPlan, config,
                      state: State, heads: int) -> jax.Array:
    """q [B, n_dup_all, heads, D] of the protected tokens, un-merged (their own rows, on every
    device): the authors append every protected token once more to the sequence, so
    each is a query of its own."""
    idx = state.protected_pos
    rows = state.layout.take_rows(x, idx, plan.per_frame)
    (q,) = layers.block_qkv(p_block, rows, heads, pos.frame_rows(idx % plan.per_frame), dtype=config.compute_dtype,
                            parts="q")
    return q


def own_rows(plan: LayerPlan, x: jax.Array, state: State) -> jax.Array | None:
    """With `n_dup` or `protected_rows`: [B, N_local] int32, for each of this device's
    tokens the index of its own row among the protected tokens' rows when it is a
    protected dst, else -1. The
    authors' unmerge writes the protected tokens' rows last, so a protected dst takes the
    output of its own query, not its group's (the src merged into it keep the group's).
    A protected src is never merged: its group's row is its own already."""
    if not (plan.n_dup_all or plan.protected_rows):
        return None
    b, n = x.shape[:2]
    idx = state.protected_pos  # [B, n_dup_all] global positions, dst first
    rel = idx - state.layout.offset(plan.per_frame)
    is_dst = jnp.take(jnp.asarray(plan.partition.is_dst), idx, mode="clip")
    mine = is_dst & (rel >= 0) & (rel < n)
    slot = jnp.broadcast_to(jnp.arange(idx.shape[1], dtype=jnp.int32), idx.shape)
    return jnp.full((b, n), -1, jnp.int32).at[jnp.arange(b)[:, None], jnp.where(mine, rel, n)].set(slot, mode="drop")


def attend_duplicates(qm: jax.Array, keys: Keys, plan: LayerPlan, config, state: State, dyn: int | None = None
                      ) -> jax.Array:
    """`attend` for a layer with the protected tokens' own rows: qm [B, rows + n_dup_all,
    H, D], keys ending in their n_dup_all slots (dst first) -> [B, rows + n_dup_all, H, D].
    On one device the rows and slots beyond n_dup are left out (their outputs 0: they are
    protected src, whose own rows nobody reads, and whose slots are masked); under
    saliency protection a sequence with more than n_dup protected dst takes every row
    (`lax.cond`: the values do not depend on the branch). Over devices all of them.
    `dyn`: the dynamic K/V slots among the keys (`within_capacity`)."""
    extra = plan.n_dup_all - plan.n_dup
    if state.layout.sharded or not extra:
        return attend(qm, keys, plan, config, plan.n_dup_all, dyn)

    def capped(qm, keys):
        m = keys.k.shape[1] - extra
        cut = Keys(keys.k[:, :m], keys.v[:, :m], keys.sizes[:, :m], keys.valid[:, :m], None)
        out = attend(qm[:, :qm.shape[1] - extra], cut, plan, config, dyn=dyn)
        return jnp.pad(out, ((0, 0), (0, extra), (0, 0), (0, 0)))

    if config.compression.protect == "stride":  # the protected dst are the first n_dup, statically
        return capped(qm, keys)
    is_dst = jnp.take(jnp.asarray(plan.partition.is_dst), state.protected_pos, mode="clip")
    overflow = jnp.any(jnp.sum(is_dst, axis=1) > plan.n_dup)
    return jax.lax.cond(overflow, lambda q, k: attend(q, k, plan, config, plan.n_dup_all, dyn),
                        capped, qm, keys)


def attend(qm: jax.Array, keys: Keys, plan: LayerPlan, config, dup: int | None = None,
           dyn: int | None = None) -> jax.Array:
    """The merged queries [B, rows, H, D] (then, with `n_dup`, the protected tokens' own
    queries [B, dup, H, D], dup defaulting to n_dup) against the layer's keys (`dyn`
    dynamic slots among them, default n_dyn), with the size bias log g (and the invalid
    slots masked) -> [B, rows (+ dup), H, D]."""
    comp = config.compression
    dup = plan.n_dup if dup is None else dup
    layout = frame_layout(frames=plan.frames)

    def bias(g, valid, masked):
        if not plan.size_column and not masked:
            return None
        return log_sizes(g if comp.size_bias and plan.size_column else jnp.ones_like(g), valid if masked else None)

    if layout.sharded:
        # (the padding rows are always masked; log 1 = 0 keeps a layer without the size
        # column exact)
        dup = keys.dup
        extra = () if dup is None else ((dup[0], dup[1], bias(dup[2], dup[3], plan.masked)),)
        log_g = bias(keys.sizes, keys.valid, True)
        # Q and K made after V's sums (else they sit through V's sums)
        return ring_attention(ordered_after(qm, keys.v), ordered_after(keys.k, keys.v), keys.v, log_g, layout,
                              extra, implementation=config.attention)
    log_g = bias(keys.sizes, keys.valid, plan.masked) if plan.size_column else None
    check_shapes(plan, comp, qm.shape[1] - dup, keys.k, log_g, dup, dyn)
    return attention(qm, keys.k, keys.v, log_g, implementation=config.attention)


def unmerge_block(p_block: Params, x: jax.Array, out: jax.Array, share: MergedRows, plan: LayerPlan, config,
                  own: jax.Array | None = None) -> jax.Array:
    """The block around the merged attention: its hook unmerges the projected merged rows
    out [B, rows (+ n_dup_all), C], each token taking its group's row (over devices, the
    rows travel around the ring), or with `own` ([B, N] from `own_rows`) a protected dst
    its own row (the n_dup_all rows after the merged ones; every device holds them all)."""
    cfg = layers.BlockConfig.of(config)
    group = share.group
    layout = frame_layout(frames=plan.frames)
    if not layout.sharded:
        if own is not None:
            group = jnp.where(own >= 0, share.rows + own, group)
        return layers.chunked_block(p_block, x, lambda gc: lambda h: merge_lib.unmerge(out, gc), (group,), cfg)
    rows = layout.ring_take(out[:, :share.rows], group)
    if own is not None:
        mine = chunks.take_along(out[:, share.rows:], jnp.maximum(own, 0), axis=1)
        rows = jnp.where((own >= 0)[..., None], mine, rows)
    return layers.chunked_block(p_block, x, lambda rc: lambda h: rc, (rows,), cfg)
