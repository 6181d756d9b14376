"""Matching: every src token's most similar dst token by cosine similarity, static
shapes and bounded memory (the similarities made and reduced a block of src rows at a
time, the whole [N_src, N_dst] matrix never formed), on one device or over devices.

`best_match` is what `merge.compute_match` calls; the argmax is the first dst reaching a
row's max (ties to the lowest index), as a stable descending sort puts first.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops import chunks
from rvggt_jax.ops.shards import FrameShards, frame_layout
from rvggt_jax.ops.ordering import materialize


def normalize(x: jax.Array, eps: float = 1e-6) -> jax.Array:
    """Rows scaled to unit L2 norm (zero rows stay zero)."""
    return x * jax.lax.rsqrt(jnp.maximum(jnp.sum(x * x, axis=-1, keepdims=True), eps * eps))


# Bytes of one block of float32 cosine similarities [rows, N_dst]: blocks that stay in
# cache for the reductions (the whole matrix is [N_src, N_dst]).
SIMILARITY_BLOCK_BYTES = 8 * 2**20


def best_match(metric: jax.Array, src_idx: np.ndarray, dst_idx: np.ndarray, chunk: int = 0,
               dtype=None, transform=None, per_frame: int = 0) -> tuple[jax.Array, jax.Array]:
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
    devices (`_match_over_devices`, with the frames split over devices: metric holds this
    device's tokens, `per_frame` per frame; every device's dst rows travel around the
    ring), and within groups (`_match_within_groups`: each group, a frame, on the device
    that holds it)."""
    unit = _UnitRows(metric, metric.dtype if dtype is None else dtype, transform)
    shards = frame_layout(metric.shape[1] // per_frame) if per_frame else None
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


# Columns per chunk of `_best`'s two-level argmax (the divisor of the dst count nearest
# to it, from 8 to 32; without one, one level).
ARGMAX_CHUNK = 16


def _chunk_width(n: int) -> int | None:
    """The divisor of n in [8, 32] nearest to ARGMAX_CHUNK (the smaller on a tie), or None."""
    widths = [c for c in range(8, 33) if n % c == 0]
    return min(widths, key=lambda c: (abs(c - ARGMAX_CHUNK), c)) if widths else None


def _best(a: jax.Array, d: jax.Array, nb: int, rank: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """Unit rows a [..., Na, C] against d [..., Nb', C] -> (max cosine, argmax) [..., Na]:
    argmax as an index into the group's nb dst, the first one reaching the max (ties to
    the lowest index; a row of NaN features gets the last index). `rank`: a device's dst
    block's ranks in the whole dst list, -1 for padding slots."""
    sims = jnp.einsum("...ic,...jc->...ij", a, d, preferred_element_type=jnp.float32)
    c = _chunk_width(sims.shape[-1])
    if rank is not None or c is None:
        # one level: the max, then the first index reaching it (a select XLA:CPU writes
        # out and reads again; its argmax, a variadic reduce, is 3x slower)
        if rank is not None:
            sims = jnp.where(rank >= 0, sims, -jnp.inf)
        top = jnp.max(sims, axis=-1)
        first = _first_reaching(sims, top, rank, nb)
        return top, jnp.minimum(first, nb - 1).astype(jnp.int32)
    # Two levels, so that the similarities are read once after the matmul writes them:
    # the max of every chunk of c columns, the row's max from those, the first chunk
    # holding it, then the first column of that chunk reaching it. Indices as float32:
    # exact below 2^24.
    chunks_n = sims.shape[-1] // c
    blocks = sims.reshape(sims.shape[:-1] + (chunks_n, c))
    # (the barrier: else XLA folds the max of the chunk maxima into a second pass over
    # every similarity)
    top_c = materialize(jnp.max(blocks, axis=-1))  # [..., Na, chunks]
    top = jnp.max(top_c, axis=-1)
    k = _first_reaching(top_c, top).astype(jnp.int32)  # chunks_n where none (a NaN row)
    chunk = jnp.take_along_axis(blocks, jnp.minimum(k, chunks_n - 1)[..., None, None], axis=-2,
                                mode="promise_in_bounds")[..., 0, :]
    col = _first_reaching(chunk, top)
    # (none in the chunk: a NaN row, whose chunk maxima XLA:CPU may take as -inf)
    first = jnp.where(col < c, k.astype(jnp.float32) * c + col, np.float32(nb))
    return top, jnp.minimum(first, nb - 1).astype(jnp.int32)


def _first_reaching(x: jax.Array, top: jax.Array, index: jax.Array | None = None, none: int | None = None
                    ) -> jax.Array:
    """x [..., n], top [...] -> the first index (float32) along the last axis with x >= top,
    `none` (default n) where none does (top NaN). `index` [n] float32: the columns'
    indices (default 0..n-1; a device's dst block passes its ranks)."""
    n = x.shape[-1]
    index = jnp.arange(n, dtype=jnp.float32) if index is None else index
    return jnp.min(jnp.where(x >= top[..., None], index, np.float32(n if none is None else none)), axis=-1)


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
