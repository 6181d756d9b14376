"""Bipartite token merging with static shapes: the match (from `matching.best_match`),
group ids, sizes, merge, unmerge.

A *match* (`Match`, what the band cache stores) is the group of every token, the group
sizes and the unmerged src tokens.

Merging averages q, k, v (after qk-norm and RoPE) over each group; unmerging gives
every token its group's row.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from rvggt_jax.ops import chunks
from rvggt_jax.ops.ordering import materialize, zeros_after
from rvggt_jax.compression.matching import best_match
from rvggt_jax.compression.plan import LayerPlan


class Match(NamedTuple):
    """The data-dependent result of matching (a pytree)."""

    group: jax.Array  # [B, N] int32: every token's group in the query layout [dst (N_dst) ; unmerged src (U)]
    sizes: jax.Array  # [B, N_m] float32: g = 1 + number of src merged into a dst, 1 for an
    # unmerged src, 0 for an empty row (its src merged beyond the static r: `LayerPlan.r_max`)
    unm_pos: jax.Array  # [B, U] int32: positions of the unmerged src, in query-layout order

    @classmethod
    def zeros(cls, plan: LayerPlan, batch: int) -> "Match":
        """A match of the plan's shapes filled with zeros (the initial carry of a band's scan)."""
        return cls(jnp.zeros((batch, plan.tokens), jnp.int32), jnp.zeros((batch, plan.n_query), jnp.float32),
                   jnp.zeros((batch, plan.n_unm), jnp.int32))


# Score of protected src: below every cosine similarity, so never among the top r.
PROTECTED_SCORE = -4.0


def ordered_bits(score: jax.Array) -> jax.Array:
    """float32 (or float64) -> uint32 (uint64) in the same order, -0.0 equal to 0.0 and
    NaN lowest (as a sort compares them): negative floats have every bit flipped, the
    others their sign bit."""
    if jnp.dtype(score.dtype).itemsize < 4:
        score = score.astype(jnp.float32)
    nbits = jnp.dtype(score.dtype).itemsize * 8
    utype = jnp.dtype(f"uint{nbits}")
    score = jnp.where(score == 0, jnp.zeros((), score.dtype), score)
    bits = jax.lax.bitcast_convert_type(score, utype)
    flip = jnp.where(bits >> (nbits - 1) == 1, jnp.array(-1).astype(utype), jnp.array(1 << (nbits - 1), utype))
    return jnp.where(jnp.isnan(score), jnp.zeros((), utype), bits ^ flip)


def compact(valid: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
    """valid [B, P] bool -> (indices [B, n] of the first n True entries, then False ones;
    their validity [B, n]). Stable: True entries keep their order."""
    # Each entry's place in that order, from running counts, then scattered: a stable
    # argsort of ~valid, without a sort (XLA:GPU compiles a sort it has no library call
    # for, as in a compile without the device, into a kernel that takes seconds to build).
    b, p = valid.shape
    n = min(n, p)
    ones = valid.astype(jnp.int32)
    trues_before = jnp.cumsum(ones, axis=-1) - ones
    falses_before = jnp.arange(p, dtype=jnp.int32) - trues_before
    place = jnp.where(valid, trues_before, jnp.sum(ones, axis=-1, keepdims=True) + falses_before)
    order = jnp.zeros((b, n), jnp.int32).at[jnp.arange(b)[:, None], place].set(
        jnp.broadcast_to(jnp.arange(p, dtype=jnp.int32), (b, p)), mode="drop", unique_indices=True)
    return order, jnp.take_along_axis(valid, order, axis=-1, mode="promise_in_bounds")


def select_best(score: jax.Array, r: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The r highest scores of each row of score [..., n], ties to the lower index (the
    set a stable sort by descending score puts first) -> (merged [..., n] bool, rank
    [..., n] int32: an unselected entry's place among the unselected, in index order,
    unselected [..., n - r] int32: their indices in index order).

    No sort: the r-th highest score is found bit by bit (32 counting passes over the
    row, on the scores' order-preserving bits, `ordered_bits`), then the ties at it taken in index
    order. XLA:GPU, where it has no library sort (a compile without the device), builds
    its own sort kernel for each sort of a program, seconds of compile per sort; and the
    rows come out in index order, which no result depends on (the merged rows are a set
    of keys and queries)."""
    n = score.shape[-1]
    lead = score.shape[:-1]
    if r <= 0:
        merged = jnp.zeros(score.shape, bool)
    elif r >= n:
        merged = jnp.ones(score.shape, bool)
    else:
        key = ordered_bits(score)
        nbits = key.dtype.itemsize * 8

        def bit(i, t):  # t: the highest value with at least r keys >= t, built from the top bit
            cand = t | (jnp.ones((), key.dtype) << (nbits - 1 - i).astype(key.dtype))
            enough = jnp.sum((key >= cand[..., None]).astype(jnp.int32), axis=-1) >= r
            return jnp.where(enough, cand, t)

        t = jax.lax.fori_loop(0, nbits, bit, jnp.zeros(lead, key.dtype))[..., None]
        above = key > t
        ties = key == t
        need = r - jnp.sum(above.astype(jnp.int32), axis=-1, keepdims=True)
        merged = above | (ties & (jnp.cumsum(ties.astype(jnp.int32), axis=-1) <= need))
    rest = (~merged).astype(jnp.int32)
    rank = jnp.cumsum(rest, axis=-1) - rest
    u = n - max(0, min(r, n))
    unselected, _ = compact(~merged.reshape(-1, n), u)
    return merged, rank, unselected.reshape(lead + (u,))


def compute_match(metric: jax.Array, protected_src: jax.Array | None, plan: LayerPlan, chunk: int, dtype=None,
                  transform=None, protected_pos: jax.Array | None = None) -> Match:
    """metric [B, N, C] (similarity features), protected_src [B, N_src] bool or None ->
    the `Match` of this layer's plan (its partition: `plan.partition`). With
    `plan.protected_rows`, row N_dst + j is the own row of protected token j of
    protected_pos [B, U] (a protected dst's has no member: the block writes its own q, k,
    v there, `merged_layer.own_qkv`). The unit rows are
    normalised in float32 and stored in `dtype` (default: the metric's) block by block;
    the cosine similarities accumulate in float32 (`best_match`). With the frames split
    over devices (`ops.shards.frame_layout`): metric holds this device's tokens; the
    match is sequence-wide, the same on every device."""
    found = dict(chunk=chunk, dtype=dtype, transform=transform, per_frame=plan.per_frame)
    part = plan.partition
    b = metric.shape[0]
    n_dst, n_src, r, U = plan.n_dst, plan.n_src, plan.r, plan.n_unm

    if plan.scope == "sequence":
        matched = None if protected_src is None else plan.matched_src
        src_pos = part.src_pos if matched is None else part.src_pos[matched]
        score, arg = best_match(metric, src_pos[None], part.dst_pos[None], **found)
        score, arg = score[:, 0], arg[:, 0]  # [B, N_src] (or the matched src), arg indexes dst_pos
        if matched is not None:  # the statically protected src: never merged, their arg unused
            score = jnp.full((b, n_src), PROTECTED_SCORE, score.dtype).at[:, matched].set(score)
            arg = jnp.zeros((b, n_src), arg.dtype).at[:, matched].set(arg)
        if protected_src is not None:
            score = jnp.where(protected_src, PROTECTED_SCORE, score)
        if plan.protected_rows:
            merged, group_src, unm_pos = _protected_rows(arg, protected_src, protected_pos, plan)
        else:
            merged, rank, unmerged = select_best(score, r)
            if plan.r_max > r:
                # the authors' count: every unprotected src among the r_max best merges, as
                # many more than the static r as there are protected dst; the extra ones keep
                # their row of the static layout, empty (size 0)
                merged = select_best(score, plan.r_max)[0]
                if protected_src is not None:
                    merged = merged & ~protected_src
            group_src = jnp.where(merged, arg, n_dst + rank)
            unm_pos = jnp.take(jnp.asarray(part.src_pos, jnp.int32), unmerged, mode="clip")
    else:
        s1, n_src_f = part.src_pos_f.shape
        r_f = plan.r_frame
        u_f = n_src_f - r_f
        # [B, S-1, n_src_f], arg local to the frame's dst
        score, arg = best_match(metric, part.src_pos_f, part.dst_pos[part.dst_rank_f], **found)
        arg = jnp.take(jnp.asarray(part.dst_rank_f, jnp.int32), arg + jnp.arange(s1, dtype=jnp.int32)[:, None]
                       * part.dst_rank_f.shape[1], mode="clip")
        if protected_src is not None:
            score = jnp.where(protected_src.reshape(b, s1, n_src_f), PROTECTED_SCORE, score)
        merged, rank, unmerged = select_best(score, r_f)
        frame_base = n_dst + jnp.arange(s1, dtype=jnp.int32)[:, None] * u_f
        group_src = jnp.where(merged, arg, frame_base + rank).reshape(b, n_src)
        merged = merged.reshape(b, n_src)
        unm_pos = jnp.take_along_axis(jnp.broadcast_to(jnp.asarray(part.src_pos_f, jnp.int32), unmerged.shape[:-1]
                                                       + part.src_pos_f.shape[-1:]),
                                      unmerged, axis=-1, mode="promise_in_bounds").reshape(b, U)

    group_src = group_src.astype(jnp.int32)
    dst_ranks = jnp.broadcast_to(jnp.arange(n_dst, dtype=jnp.int32), (b, n_dst))
    group = jnp.take(jnp.concatenate([dst_ranks, group_src], axis=1), part.perm_to_pos, axis=1, mode="clip")
    counts = jax.vmap(lambda g, w: jax.ops.segment_sum(w, g, num_segments=n_dst + 1))(
        jnp.where(merged, group_src, n_dst), merged.astype(jnp.float32))[:, :n_dst]
    unm_sizes = jnp.ones((b, U), jnp.float32)
    if plan.r_max > r and not plan.protected_rows:  # an unmerged row whose src merged after all is empty
        unm_sizes = 1.0 - jnp.take_along_axis(merged, unmerged, axis=1, mode="promise_in_bounds").astype(jnp.float32)
    sizes = jnp.concatenate([1.0 + counts, unm_sizes], axis=1)
    return Match(group, sizes, unm_pos.astype(jnp.int32))


def _protected_rows(arg: jax.Array, protected_src: jax.Array, protected_pos: jax.Array, plan: LayerPlan):
    """(merged [B, N_src], group_src [B, N_src], unm_pos [B, U]) when every unprotected
    src merges into its best dst (arg [B, N_src]) and the U rows are the protected
    tokens' own rows in protected_pos [B, U] order: a protected src's group is its row."""
    b, u = protected_pos.shape
    if u != plan.n_unm:
        raise ValueError(f"global block {plan.layer}: its U = {plan.n_unm} rows are the protected tokens' own "
                         f"rows, but {u} tokens are protected")
    row_of = jnp.full((b, plan.tokens), -1, jnp.int32).at[jnp.arange(b)[:, None], protected_pos].set(
        jnp.broadcast_to(plan.n_dst + jnp.arange(u, dtype=jnp.int32), (b, u)), mode="drop")
    own_src = jnp.take(row_of, plan.partition.src_pos, axis=1, mode="clip")
    return ~protected_src, jnp.where(protected_src, own_src, arg), protected_pos


def mean_divisor(sizes: jax.Array) -> jax.Array:
    """What a group's sum is divided by for its mean: its size, 1 for an empty row (its
    sums are 0: its mean 0; it is no key and nobody's group)."""
    return jnp.maximum(sizes, 1.0)


def merge(x: jax.Array, match: Match, n_query: int) -> jax.Array:
    """x [B, N, F] -> group means [B, N_m, F] in x's dtype, summed in float32."""
    return merge_map(lambda xc: (xc,), (x,), match, n_query, x.shape[-1] * 4)[0]


def merge_map(fn, inputs: tuple, match: Match, n_query: int, bytes_per_row: int, dep: jax.Array | None = None,
              owned: bool = False) -> tuple:
    """Group means of per-token values that are never formed for the whole sequence:
    `fn(*chunks) -> (values [B, r, ...], ...)` over token chunks of the inputs (axis 1),
    each chunk added into float32 sums [B, N_m, ...] at its tokens' groups, then divided
    by the group sizes. Returns the means [B, N_m, ...] in each value's dtype. With `fn`
    the Q/K/V projection of a block, merging needs no full-sequence Q, K or V.

    dep: the float32 sums are made after this value (default the first input): one
    merge_map after another then holds one set of sums at a time. owned: returns
    (inputs[0], means...), the first input passing through the loop
    (`chunks.fold_tokens_through`: the residual stream stays one buffer)."""
    x0 = inputs[0]
    b, n = x0.shape[:2]
    offsets = (jnp.arange(b, dtype=jnp.int32) * n_query)[:, None]
    rows = chunks.row_chunks(n, b * bytes_per_row)
    spec = jax.eval_shape(fn, *[chunks.dynamic_slice(t, 0, min(rows, n), 1) for t in inputs])
    sums = tuple(zeros_after((b * n_query,) + o.shape[2:], jnp.float32, x0 if dep is None else dep)
                 for o in spec)

    def add(acc, group, *chunk):
        ids = (group + offsets).reshape(-1)
        vals = fn(*chunk)
        return tuple(a.at[ids].add(v.reshape((-1,) + v.shape[2:]).astype(jnp.float32), mode="promise_in_bounds")
                     for a, v in zip(acc, vals))

    group = match.group
    if rows >= n:
        sums = add(sums, group, *map(chunks.whole, inputs))
    elif owned:
        x0, sums = chunks.fold_tokens_through(lambda acc, xc, g, *c: add(acc, g, xc, *c), x0, sums,
                                              (group, *inputs[1:]), n, rows)
    else:
        sums = chunks.fold_tokens(lambda acc, start, size, *c: add(acc, *c), sums, (group, *inputs), n, 1, rows)
    sums = tuple(a.reshape((b, n_query) + a.shape[1:]) for a in sums)
    sizes = mean_divisor(match.sizes)
    means = materialized(tuple((a / sizes.reshape(sizes.shape + (1,) * (a.ndim - 2))).astype(o.dtype)
                               for a, o in zip(sums, spec)))
    return (x0, *means) if owned else means


def materialized(means):
    """The means as buffers of their own dtype, made here: else XLA fuses the division
    and the cast into their consumers, the attention much later, and the float32 sums stay
    alive until then (a later `zeros_after(mean)` reads one element straight from the sum).
    In XLA:GPU's plan of `regime` at 1000 frames, q's and k's sums were alive next to v's
    (3 x 2.1 GB where one was meant to be)."""
    return materialize(means)


def block_sums(values: jax.Array, group: jax.Array, rows: int, into: jax.Array | None = None) -> jax.Array:
    """Float32 sums [B, rows, ...] of values [B, N, ...] over the groups group [B, N]
    (tokens whose group is outside [0, rows) are left out), added to `into` (default
    zeros): one block of the group sums (over devices, the block `ring_sum_scatter` is
    making, added in place to the sum received). Token chunks are cast to float32 and
    added one at a time (a float32 copy of all the values would be hoisted out of the
    ring as a loop invariant)."""
    b, n = values.shape[:2]
    offsets = (jnp.arange(b, dtype=jnp.int32) * rows)[:, None]

    def add(acc, start, size, gc, vc):
        inside = (gc >= 0) & (gc < rows)
        ids = jnp.where(inside, gc + offsets, b * rows).reshape(-1)
        return acc.at[ids].add(vc.reshape((-1,) + vc.shape[2:]).astype(jnp.float32), mode="drop")

    shape = (b * rows,) + values.shape[2:]
    sums = zeros_after(shape, jnp.float32, values) if into is None else into.reshape(shape)
    # (a quarter of a token chunk: the float32 chunk sits next to the ring's two blocks
    # of sums at the sharded forward's peak)
    chunk = chunks.row_chunks(n, b * math.prod(values.shape[2:]) * 4, chunks.TOKEN_CHUNK_BYTES // 4)
    return chunks.fold_tokens(add, sums, (group, values), n, 1, chunk).reshape((b, rows) + values.shape[2:])


def unmerge(y: jax.Array, group: jax.Array) -> jax.Array:
    """y [B, N_m, F] -> [B, N, F]: every token takes its group's row (group [B, N], a
    `Match.group` or a chunk of it)."""
    return chunks.take_along(y, group, axis=1)
