"""Per-token work over chunks of tokens, written in place.

At 1000 frames of VGGT-1B one layer holds a million tokens: everything that is per token
(norms, Q/K/V projections, RoPE, output projection, MLP) therefore runs over chunks of
TOKEN_CHUNK_BYTES. Short sequences take one chunk and no loop.

    map_tokens(fn, inputs)              fn over chunks, results stitched (new arrays)
    update_tokens(fn, x, inputs)        x with every chunk replaced by fn(chunk): in place
    map_tokens_through(fn, x, inputs)   (x, map_tokens of fn over x): x passes through
    fold_tokens(step, acc, inputs)      an accumulation (sums) over chunks
    fold_tokens_through(step, x, acc)   (x, the fold over x): x passes through

The `_through` loops return x as they got it, written back chunk by chunk, so that the
residual stream stays one buffer from one loop to the next in-place one; the loops cover
n rows with even chunks, the last one overlapping the one before, never a shorter tail.
Why: docs/memory_layout.md (what XLA's buffer assignment does otherwise).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvggt_jax.ops.bits import moved
from rvggt_jax.ops.ordering import ordered_after, zeros_after

# Bytes of the widest per-token intermediate (the MLP hidden layer [rows, 4C] in float32)
# computed at once: longer sequences run over chunks of tokens of this size.
TOKEN_CHUNK_BYTES = 128 * 2**20


def row_chunks(n_rows: int, bytes_per_row: int, chunk_bytes: int | None = None, multiple: int = 8) -> int:
    """Rows per chunk for work of `bytes_per_row` bytes per row: a multiple of `multiple`
    (8 for tokens; 1 for whole sequences), at least `multiple`; `n_rows` when everything
    fits one chunk."""
    chunk_bytes = TOKEN_CHUNK_BYTES if chunk_bytes is None else chunk_bytes
    rows = max(multiple, (chunk_bytes // max(bytes_per_row, 1)) // multiple * multiple)
    return n_rows if rows >= n_rows else rows


def dynamic_slice(x: jax.Array, start, size: int, axis: int) -> jax.Array:
    """`lax.dynamic_slice_in_dim` of an array or a `Periodic` one; 16-bit floats are sliced
    as bits (`bits.moved`: XLA:CPU would convert the whole operand to float32)."""
    if isinstance(x, Periodic):
        return x.rows_at(start, size, axis)
    return moved(lambda t, s: jax.lax.dynamic_slice_in_dim(t, s, size, axis), x, start)


def slice_rows(x, start: int, stop: int, axis: int) -> jax.Array:
    """`lax.slice_in_dim` (static bounds) of an array or a `Periodic` one."""
    if isinstance(x, Periodic):
        return x.rows_at(start, stop - start, axis)
    return jax.lax.slice_in_dim(x, start, stop, axis=axis)


@jax.tree_util.register_pytree_node_class
class Periodic:
    """An array [B, n, ...] whose rows along axis 1 repeat every `period` rows, held as one
    period [B, period, ...]: the RoPE tables of a sequence of frames (every frame has the
    same positions), which need not be tiled to the whole sequence: the chunk loops
    (`dynamic_slice`, `slice_rows`) take a chunk's rows from the period (row i is row i
    mod period), and `whole` tiles it where a loop runs in one chunk."""

    def __init__(self, period: jax.Array, n: int):
        if n % period.shape[1]:
            raise ValueError(f"a Periodic array of {n} rows needs a multiple of its period {period.shape[1]}")
        self.period, self.n = period, n

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.period.shape[0], self.n) + self.period.shape[2:]

    @property
    def dtype(self):
        return self.period.dtype

    @property
    def ndim(self) -> int:
        return self.period.ndim

    def rows_at(self, start, size: int, axis: int = 1) -> jax.Array:
        """Rows [start, start + size) along axis 1 (start may be traced)."""
        if axis != 1:
            raise ValueError(f"a Periodic array repeats along axis 1, not {axis}")
        idx = (start + jnp.arange(size, dtype=jnp.int32)) % self.period.shape[1]
        return jnp.take(self.period, idx, axis=1, mode="clip")

    def whole(self) -> jax.Array:
        reps = (1, self.n // self.period.shape[1]) + (1,) * (self.period.ndim - 2)
        return jnp.tile(self.period, reps)

    def tree_flatten(self):
        return (self.period,), self.n

    @classmethod
    def tree_unflatten(cls, n, children):
        # (no check: JAX unflattens with placeholder leaves too)
        obj = object.__new__(cls)
        obj.period, obj.n = children[0], n
        return obj


def whole(x):
    """x itself, or a `Periodic` array tiled to all its rows."""
    return x.whole() if isinstance(x, Periodic) else x


def take(x: jax.Array, idx: jax.Array, axis: int) -> jax.Array:
    """`jnp.take(x, idx, axis, mode="clip")`; 16-bit floats gathered as bits."""
    return moved(lambda t, i: jnp.take(t, i, axis=axis, mode="clip"), x, idx)


def take_along(x: jax.Array, idx: jax.Array, axis: int) -> jax.Array:
    """`jnp.take_along_axis(x, idx, axis)` (indices in bounds, idx broadcast over x's
    trailing axes), through a uint16 view for 16-bit floats."""
    idx = idx.reshape(idx.shape + (1,) * (x.ndim - idx.ndim))
    return moved(lambda t, i: jnp.take_along_axis(t, i, axis=axis, mode="promise_in_bounds"), x, idx)


def dynamic_index(x: jax.Array, index, axis: int = 0) -> jax.Array:
    """`lax.dynamic_index_in_dim(..., keepdims=False)` through `dynamic_slice`."""
    return jax.lax.squeeze(dynamic_slice(x, index, 1, axis), (axis,))


def fold_tokens(step, acc, inputs: tuple, n: int, axis: int, rows: int):
    """acc = step(acc, start, size, *chunks) over chunks of `rows` of the `n` tokens along
    `axis` of every input (a `fori_loop`), then the shorter tail: for accumulations (sums)
    that read their inputs, which the tail leaves as they are."""
    count = n // rows

    def body(i, a):
        return step(a, i * rows, rows, *[dynamic_slice(t, i * rows, rows, axis) for t in inputs])

    acc = jax.lax.fori_loop(0, count, body, acc)
    if count * rows < n:
        acc = step(acc, count * rows, n - count * rows, *[slice_rows(t, count * rows, n, axis) for t in inputs])
    return acc


def even_chunks(n: int, rows: int, multiple: int = 1) -> tuple[int, int]:
    """(count, rows') for covering n rows with chunks of at most about `rows`: the fewest
    chunks, each ceil(n / count) rows rounded up to `multiple`, so that the chunks
    overlap by less than `multiple` rows each instead of leaving a short tail."""
    count = -(-n // rows)
    size = -(-n // count)
    return count, min(n, -(-size // multiple) * multiple)


def _chunk_loop(fn, acc, inputs: tuple, n: int, axis: int, rows: int, multiple: int, reader=None,
                in_place: bool = False):
    """The chunk loop of `map_tokens`, `map_tokens_through` and `update_tokens`: `count`
    chunks of `rows` (`even_chunks`), chunk i written at min(i * rows, n - rows), so no
    shorter tail chunk updates the result a second time outside the loop (XLA would copy
    the result for it).

    Where the last chunk overlaps the one before (n not a multiple of rows): a new array
    (`in_place` False) takes the overlapped rows again, computed from the same inputs; an
    array updated in place (`in_place`, `update_tokens`) keeps them (masked), since they
    are already updated. Only an update in place reads back what the loop wrote (for a
    16-bit array XLA:CPU makes that read a copy of the whole array per step).

    fn(chunk of reader(acc) or None, *input_chunks) -> the chunk's new values (a pytree
    like acc)."""
    count, rows = even_chunks(n, rows, multiple)
    overlap = in_place and count * rows != n

    def body(i, a):
        start = jnp.minimum(i * rows, n - rows)

        def chunk_of(tree):
            # (a Periodic input is sliced as one array, not as the pytree it also is)
            return jax.tree.map(lambda t: dynamic_slice(t, start, rows, axis), tree,
                                is_leaf=lambda t: isinstance(t, Periodic))

        res = fn(None if reader is None else chunk_of(reader(a)), *chunk_of(inputs))
        if overlap:  # the rows before i * rows are done (only in the last chunk)
            fresh = jax.lax.broadcasted_iota(jnp.int32, (rows,), 0) >= i * rows - start

            def keep(r, o):
                return jnp.where(fresh.reshape((1,) * axis + (rows,) + (1,) * (r.ndim - axis - 1)), r, o)

            res = jax.tree.map(keep, res, chunk_of(a))
        return jax.tree.map(lambda t, r: jax.lax.dynamic_update_slice_in_dim(t, r, start, axis), a, res)

    return jax.lax.fori_loop(0, count, body, acc)


def fold_tokens_through(step, x: jax.Array, acc, inputs: tuple, n: int, rows: int):
    """(x, acc) with acc = step(acc, x_chunk, *input_chunks) over chunks of `rows` tokens
    (axis 1) of x and the inputs, as `fold_tokens`; x passes through the loop (each chunk
    written back unchanged, as in `map_tokens_through`). The shorter tail only reads x."""
    count = n // rows

    def body(i, carry):
        xs, a = carry
        xc = dynamic_slice(xs, i * rows, rows, 1)
        a = step(a, xc, *[dynamic_slice(t, i * rows, rows, 1) for t in inputs])
        return jax.lax.dynamic_update_slice_in_dim(xs, ordered_after(xc, a), i * rows, 1), a

    x, acc = jax.lax.fori_loop(0, count, body, (x, acc))
    if count * rows < n:
        acc = step(acc, *[slice_rows(t, count * rows, n, 1) for t in (x, *inputs)])
    return x, acc


def _zero_results(fn, chunk_inputs: list, n: int, axis: int, dep: jax.Array):
    """Zero buffers, made after `dep`, for fn's outputs stitched over all `n` rows along
    `axis` (fn's output shapes from one chunk of its inputs)."""
    def full(o):
        shape = list(o.shape)
        shape[axis] = n
        return zeros_after(tuple(shape), o.dtype, dep)

    return jax.tree.map(full, jax.eval_shape(fn, *chunk_inputs))


def map_tokens(fn, inputs: tuple, axis: int = 1, rows: int | None = None, bytes_per_row: int = 0,
               dep: jax.Array | None = None, multiple: int = 8):
    """`fn(*chunks) -> pytree` over chunks of `rows` tokens along `axis` of every input,
    the results stitched along the same axis (written into zero buffers made after `dep`,
    default the first input). `rows` defaults to `row_chunks(n, bytes_per_row)`; `fn`
    must be token-independent along `axis`."""
    n = inputs[0].shape[axis]
    rows = row_chunks(n, bytes_per_row, multiple=multiple) if rows is None else rows
    if rows >= n:
        return fn(*map(whole, inputs))
    _, size = even_chunks(n, rows, multiple)
    outs = _zero_results(fn, [dynamic_slice(t, 0, size, axis) for t in inputs], n, axis,
                         inputs[0] if dep is None else dep)
    return _chunk_loop(lambda _, *c: fn(*c), outs, inputs, n, axis, rows, multiple)


def map_tokens_through(fn, x: jax.Array, inputs: tuple = (), axis: int = 1, rows: int | None = None,
                       bytes_per_row: int = 0, multiple: int = 8, dep: jax.Array | None = None):
    """(x, fn(x_chunk, *input_chunks) stitched as in `map_tokens`), x passing through the
    loop: each chunk of x is written back unchanged, so that x stays the buffer the next
    in-place loop updates (a loop that only reads x makes XLA copy it for that loop).
    dep: the outputs are made after this value (default x), as in `map_tokens`."""
    n = x.shape[axis]
    rows = row_chunks(n, bytes_per_row, multiple=multiple) if rows is None else rows
    if rows >= n:
        return x, fn(x, *map(whole, inputs))
    _, size = even_chunks(n, rows, multiple)
    outs = _zero_results(fn, [dynamic_slice(t, 0, size, axis) for t in (x, *inputs)], n, axis,
                         x if dep is None else dep)

    def both(xc, *c):
        out = fn(xc, *c)
        return ordered_after(xc, out), out

    return _chunk_loop(both, (x, outs), inputs, n, axis, rows, multiple, lambda a: a[0])


def update_tokens(fn, x: jax.Array, inputs: tuple = (), axis: int = 1, rows: int | None = None,
                  bytes_per_row: int = 0, multiple: int = 8) -> jax.Array:
    """x with every chunk of `rows` tokens along `axis` replaced by `fn(x_chunk,
    *input_chunks)` (same shape and dtype), in place: the residual stream is updated
    without a second copy (x's chunk is read from the loop's own buffer)."""
    n = x.shape[axis]
    rows = row_chunks(n, bytes_per_row, multiple=multiple) if rows is None else rows
    if rows >= n:
        return fn(x, *map(whole, inputs))
    return _chunk_loop(fn, x, inputs, n, axis, rows, multiple, lambda a: a, in_place=True)
