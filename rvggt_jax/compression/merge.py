"""Bipartite token merging with static shapes: matching, group ids, sizes, merge, unmerge.

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
import numpy as np

from rvggt_jax.ops import chunks
from rvggt_jax.ops.ordering import zeros_from
from rvggt_jax.ops.shards import FrameShards
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


def normalize(x: jax.Array, eps: float = 1e-6) -> jax.Array:
    """Rows scaled to unit L2 norm (zero rows stay zero)."""
    return x * jax.lax.rsqrt(jnp.maximum(jnp.sum(x * x, axis=-1, keepdims=True), eps * eps))


# Bytes of one block of float32 cosine similarities [rows, N_dst]: blocks that stay in
# cache for the two reductions (the whole matrix is [N_src, N_dst]).
SIMILARITY_BLOCK_BYTES = 8 * 2**20


def best_match(metric: jax.Array, src_idx: np.ndarray, dst_idx: np.ndarray, chunk: int = 0,
               dtype=None, transform=None, shards: FrameShards | None = None, per_frame: int = 0
               ) -> tuple[jax.Array, jax.Array]:
    """Cosine matching of src to dst tokens, in blocks.

    metric [B, N, C] (features, not yet normalised); src_idx [G, Na] and dst_idx [G, Nb]
    static token positions in G groups (G = 1: every src against every dst; G = S - 1:
    each frame's src against its own dst). Returns (max cosine, argmax as an index into
    the group's dst_idx), each [B, G, Na]. Unit rows are made per block (normalised in
    float32, stored in `dtype`, default the metric's); similarities accumulate in float32,
    at most SIMILARITY_BLOCK_BYTES of them (and at most `chunk` src rows, when > 0) at a
    time: the [Na, Nb] similarities never exist.
    `transform` (per token, e.g. the block's norm1) is applied to gathered rows first.

    Three algorithms: the whole sequence on one device (`_match_sequence`) or over
    devices (`_match_over_devices`: metric holds this device's tokens, `per_frame` per
    frame; every device's dst rows travel around the ring), and within groups
    (`_match_within_groups`: each group, a frame, on the device that holds it)."""
    unit = _UnitRows(metric, metric.dtype if dtype is None else dtype, transform)
    sharded = shards is not None and shards.sharded
    if src_idx.shape[0] > 1:
        return _match_within_groups(unit, src_idx, dst_idx, shards if sharded else None, per_frame)
    if sharded:
        score, arg = _match_over_devices(unit, src_idx[0], dst_idx[0], chunk, shards, per_frame)
    else:
        score, arg = _match_sequence(unit, src_idx[0], dst_idx[0], chunk)
    return score[:, None], arg[:, None]


class _UnitRows(NamedTuple):
    """Unit rows of the metric's tokens: gathered, transformed, normalised in float32,
    stored in `dtype`."""

    metric: jax.Array
    dtype: object
    transform: object

    def of(self, rows: jax.Array) -> jax.Array:
        rows = rows if self.transform is None else self.transform(rows)
        return normalize(rows.astype(jnp.float32)).astype(self.dtype)

    def at(self, idx: jax.Array) -> jax.Array:
        """[B, M, C] unit rows of the tokens idx [M], a chunk of tokens at a time (the
        float32 rows of all tokens never exist)."""
        per_row = self.metric.shape[0] * self.metric.shape[-1] * 4 * 3
        return chunks.map_tokens(lambda i: self.of(chunks.take(self.metric, i[0], axis=1)), (idx[None],),
                                 bytes_per_row=per_row, dep=self.metric)


# Columns per chunk of `_best`'s two-level argmax.
ARGMAX_CHUNK = 16


def _best(a: jax.Array, d: jax.Array, nb: int, rank: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """Unit rows a [..., Na, C] against d [..., Nb', C] -> (max cosine, argmax) [..., Na]:
    argmax as an index into the group's nb dst, the first one reaching the max (ties to
    the lowest index; a row of NaN features gets the last index). `rank`: a device's dst
    block's ranks in the whole dst list, -1 for padding slots."""
    sims = jnp.einsum("...ic,...jc->...ij", a, d, preferred_element_type=jnp.float32)
    if rank is not None:
        sims = jnp.where(rank >= 0, sims, -jnp.inf)
        top = jnp.max(sims, axis=-1)
        first = jnp.min(jnp.where(sims >= top[..., None], rank, np.float32(nb)), axis=-1)
        return top, jnp.minimum(first, nb - 1).astype(jnp.int32)
    # Two levels, so that the similarities are read once after the matmul writes them:
    # the max of every chunk of ARGMAX_CHUNK columns, the row's max from those, the first
    # chunk holding it, then the first column of that chunk reaching it. (XLA:CPU's
    # argmax is a variadic reduce, 3x slower; a first-index-reaching-the-max pass over
    # the whole row is one select YNNPACK does not fuse: written out and read again.)
    # Indices as float32: exact below 2^24.
    c = ARGMAX_CHUNK
    if sims.shape[-1] % c:  # (columns of -inf: never a max, NaN aside)
        sims = jnp.pad(sims, [(0, 0)] * (sims.ndim - 1) + [(0, c - sims.shape[-1] % c)], constant_values=-jnp.inf)
    chunks_n = sims.shape[-1] // c
    blocks = sims.reshape(sims.shape[:-1] + (chunks_n, c))
    # (the barrier: else XLA folds the max of the chunk maxima into a second pass over
    # every similarity)
    top_c = jax.lax.optimization_barrier(jnp.max(blocks, axis=-1))  # [..., Na, chunks]
    top = jnp.max(top_c, axis=-1)
    k = _first_reaching(top_c, top).astype(jnp.int32)
    chunk = jnp.take_along_axis(blocks, jnp.minimum(k, chunks_n - 1)[..., None, None], axis=-2,
                                mode="promise_in_bounds")[..., 0, :]
    col = _first_reaching(chunk, top)
    # (none in the chunk: a NaN row, whose chunk maxima XLA:CPU may take as -inf)
    first = jnp.where(col < c, k.astype(jnp.float32) * c + col, np.float32(nb))
    return top, jnp.minimum(first, nb - 1).astype(jnp.int32)


def _first_reaching(x: jax.Array, top: jax.Array) -> jax.Array:
    """x [..., n], top [...] -> the first index (float32) along the last axis with x >= top,
    n where none does (top NaN)."""
    n = x.shape[-1]
    return jnp.min(jnp.where(x >= top[..., None], jnp.arange(n, dtype=jnp.float32), np.float32(n)), axis=-1)


def _src_rows_per_block(na: int, b: int, dst_rows: int, chunk: int) -> int:
    """Src rows per block of similarities against `dst_rows` dst rows."""
    rows = chunks.row_chunks(na, b * dst_rows * 4, SIMILARITY_BLOCK_BYTES, multiple=64)
    return min(rows, chunk) if chunk > 0 else rows


def _match_sequence(unit: _UnitRows, src_idx: np.ndarray, dst_idx: np.ndarray, chunk: int):
    """Every src [Na] against every dst [Nb] on one device -> ([B, Na], [B, Na])."""
    # the unit src rows once (gathering them block by block inside the loop is 2x
    # slower), then blocks of src rows against the dst
    src = unit.at(jnp.asarray(src_idx, jnp.int32))
    dst = unit.at(jnp.asarray(dst_idx, jnp.int32))
    rows = _src_rows_per_block(src_idx.size, src.shape[0], dst.shape[1], chunk)
    return chunks.map_tokens(lambda a: _best(a, dst, dst_idx.size), (src,), axis=1, rows=rows)


def _match_over_devices(unit: _UnitRows, src_idx: np.ndarray, dst_idx: np.ndarray, chunk: int,
                        shards: FrameShards, per_frame: int):
    """`_match_sequence` with the tokens split over devices: this device's src against
    every device's dst block, the blocks passed around the devices, the best so far kept
    (ties: the lowest rank, as one device's first-index rule); the results gathered back
    into the global src order."""
    nb = dst_idx.size
    table, order = shards.local_positions(src_idx, per_frame)
    dst_table, dst_order = shards.local_positions(dst_idx, per_frame)
    # the global rank (in dst_idx) of every slot of every device's dst, -1 for padding
    ranks = np.full(dst_table.size, -1, np.int64)
    ranks[dst_order] = np.arange(nb)
    dst_rank = shards.per_device(ranks.reshape(dst_table.shape).astype(np.float32))
    local_dst = jnp.asarray(shards.per_device(dst_table), jnp.int32)
    local_src = jnp.asarray(shards.per_device(table), jnp.int32)
    src, dst = unit.at(local_src), unit.at(local_dst)
    rows = _src_rows_per_block(local_src.shape[0], src.shape[0], dst.shape[1], chunk)

    def against(block, rank):
        return chunks.map_tokens(lambda a: _best(a, block, nb, rank), (src,), axis=1, rows=rows)

    def step(_, carry):
        (top, arg), block = carry
        block = shards.ring_shift(block)
        t2, a2 = against(*block)
        better = (t2 > top) | ((t2 == top) & (a2 < arg))
        return (jnp.where(better, t2, top), jnp.where(better, a2, arg)), block

    (score, arg), _ = jax.lax.fori_loop(1, shards.devices, step, (against(dst, dst_rank), (dst, dst_rank)))
    return shards.gather_results(score, order, 1), shards.gather_results(arg, order, 1)


def _match_within_groups(unit: _UnitRows, src_idx: np.ndarray, dst_idx: np.ndarray, shards: FrameShards | None,
                         per_frame: int):
    """Each group's src against its own dst ([G, Na], [G, Nb]) -> ([B, G, Na], [B, G, Na]),
    blocks of groups at a time; over devices (`shards`), each device matches the groups
    it holds and the results are gathered into the global group order."""
    b, nb = unit.metric.shape[0], dst_idx.shape[1]
    order = None
    if shards is not None:
        src_table, dst_table, order = _group_tables(shards, src_idx, dst_idx, per_frame)
        src_idx, dst_idx = shards.per_device(src_table), shards.per_device(dst_table)
    src_idx, dst_idx = jnp.asarray(src_idx, jnp.int32), jnp.asarray(dst_idx, jnp.int32)
    g, na = src_idx.shape
    src = unit.at(src_idx.reshape(-1)).reshape(b, g, na, -1)
    frames = chunks.row_chunks(g, b * na * nb * 4, SIMILARITY_BLOCK_BYTES, multiple=1)

    def per_frames(a, di):  # [B, F, Na, C], [F, Nb] -> [B, F, Na] each
        d = unit.of(chunks.take(unit.metric, di.reshape(-1), axis=1)).reshape(b, a.shape[1], nb, -1)
        return _best(a, d, nb)

    score, arg = chunks.map_tokens(per_frames, (src, dst_idx[None]), axis=1, rows=frames, dep=unit.metric)
    if order is None:
        return score, arg
    return shards.gather_results(score, order, 1), shards.gather_results(arg, order, 1)


def _group_tables(shards: FrameShards, src_idx: np.ndarray, dst_idx: np.ndarray, per_frame: int):
    """The groups (frames) of each device for matching within groups: (src [devices,
    G_max, Na] and dst [devices, G_max, Nb] local token indices, order [G] of the groups
    in the devices' concatenated results). Padding entries point at local row 0 (their
    results are dropped)."""
    rows = shards.local * per_frame
    owner = src_idx[:, 0] // rows
    if not np.array_equal(owner, dst_idx[:, 0] // rows) or np.any(src_idx // rows != owner[:, None]):
        raise ValueError("matching within groups needs each group's tokens on one device")
    counts = np.bincount(owner, minlength=shards.devices)
    g_max = max(1, int(counts.max()))
    src_t = np.zeros((shards.devices, g_max, src_idx.shape[1]), np.int64)
    dst_t = np.zeros((shards.devices, g_max, dst_idx.shape[1]), np.int64)
    order = np.empty(src_idx.shape[0], np.int64)
    for d in range(shards.devices):
        mine = np.flatnonzero(owner == d)
        src_t[d, :mine.size] = src_idx[mine] - d * rows
        dst_t[d, :mine.size] = dst_idx[mine] - d * rows
        order[mine] = d * g_max + np.arange(mine.size)
    return src_t, dst_t, order


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
                  transform=None, shards: FrameShards | None = None, protected_pos: jax.Array | None = None
                  ) -> Match:
    """metric [B, N, C] (similarity features), protected_src [B, N_src] bool or None ->
    the `Match` of this layer's plan (its partition: `plan.partition`). With
    `plan.protected_rows`, row N_dst + j is the own row of protected token j of
    protected_pos [B, U] (a protected dst's has no member: the block writes its own q, k,
    v there, `merged_layer.own_qkv`). The unit rows are
    normalised in float32 and stored in `dtype` (default: the metric's) block by block;
    the cosine similarities accumulate in float32 (`best_match`). Split over devices
    (`shards`): metric holds this device's tokens; the match is sequence-wide, the same
    on every device."""
    found = dict(chunk=chunk, dtype=dtype, transform=transform, shards=shards, per_frame=plan.per_frame)
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
    sums = tuple(zeros_from((b * n_query,) + o.shape[2:], jnp.float32, x0 if dep is None else dep)
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
    alive until then (a later `zeros_from(mean)` reads one element straight from the sum).
    In XLA:GPU's plan of `regime` at 1000 frames, q's and k's sums were alive next to v's
    (3 x 2.1 GB where one was meant to be)."""
    return jax.lax.optimization_barrier(means)


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
    sums = zeros_from(shape, jnp.float32, values) if into is None else into.reshape(shape)
    # (a quarter of a token chunk: the float32 chunk sits next to the ring's two blocks
    # of sums at the sharded forward's peak)
    chunk = chunks.row_chunks(n, b * math.prod(values.shape[2:]) * 4, chunks.TOKEN_CHUNK_BYTES // 4)
    return chunks.fold_tokens(add, sums, (group, values), n, 1, chunk).reshape((b, rows) + values.shape[2:])


def unmerge(y: jax.Array, group: jax.Array) -> jax.Array:
    """y [B, N_m, F] -> [B, N, F]: every token takes its group's row (group [B, N], a
    `Match.group` or a chunk of it)."""
    return chunks.take_along(y, group, axis=1)
