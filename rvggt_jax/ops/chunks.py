"""Per-token work over chunks of tokens, written in place, and loop buffers XLA cannot
hoist.

At 1000 frames of VGGT-1B one layer holds 1M tokens: a float32 MLP hidden layer of the
whole sequence is 17 GB, a projection's float32 product 4 GB. Everything that is per
token (norms, Q/K/V projections, RoPE, output projection, MLP) therefore runs over chunks
of TOKEN_CHUNK_BYTES: `map_tokens` stitches new arrays, `update_tokens` rewrites the
residual stream in place. Short sequences take one chunk and no loop.

What keeps the residual stream x (4 GB in float32 at that size) a single buffer from
layer to layer, found in XLA's buffer assignment:
- no loop leaves a shorter tail chunk to a second update outside it (`_sweep`: even
  chunks, the last one overlapping the one before); that update made XLA copy x;
- a loop that reads x and precedes an in-place pass over it owns x (`read_tokens`,
  `fold_owned`: x is written back chunk by chunk): a loop that only reads x passes it
  through, and XLA then copies x for the in-place pass.
Loop outputs and accumulators start from `zeros_after(shape, dtype, dep)`, zeros made
from a value the loop needs anyway: XLA shares a constant zero buffer between loops and
schedules it (and one copy per loop) at the start of the program, all alive at once.
16-bit buffers a loop slices are held as bits (`Bits16`), and no loop reads back what it
wrote into a new 16-bit array (XLA:CPU would copy the whole array in every step).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# Bytes of the widest per-token intermediate (the MLP hidden layer [rows, 4C] in float32)
# computed at once. Per-token work over a long sequence (1000 frames of VGGT-1B: 1M
# tokens, a 17 GB hidden layer in float32) runs over chunks of tokens of this size,
# writing into the result in place; below it, in one go.
TOKEN_CHUNK_BYTES = 128 * 2**20


def row_chunks(n_rows: int, bytes_per_row: int, chunk_bytes: int | None = None, multiple: int = 8) -> int:
    """Rows per chunk for work of `bytes_per_row` bytes per row: a multiple of `multiple`
    (8 for tokens; 1 for whole sequences), at least `multiple`; `n_rows` when everything
    fits one chunk."""
    chunk_bytes = TOKEN_CHUNK_BYTES if chunk_bytes is None else chunk_bytes
    rows = max(multiple, (chunk_bytes // max(bytes_per_row, 1)) // multiple * multiple)
    return n_rows if rows >= n_rows else rows


def is_16bit_float(x: jax.Array) -> bool:
    return x.dtype.itemsize == 2 and jnp.issubdtype(x.dtype, jnp.floating)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _via_bits(op, x: jax.Array, index: jax.Array) -> jax.Array:
    """`op(x, index)` (a slice or gather of x) on x's uint16 bits. The bitcast to integers
    has no derivative (JAX would silently give zero gradients through it), so the JVP
    applies `op` to the tangent directly: a linear map of the tangent, which reverse mode
    transposes (into a scatter-add / update of zeros)."""
    bits = op(jax.lax.bitcast_convert_type(x, jnp.uint16), index)
    return jax.lax.bitcast_convert_type(bits, x.dtype)


@_via_bits.defjvp
def _via_bits_jvp(op, primals, tangents):
    x, index = primals
    return _via_bits(op, x, index), op(tangents[0], index)


def dynamic_slice(x: jax.Array, start, size: int, axis: int) -> jax.Array:
    """`lax.dynamic_slice_in_dim`, through a uint16 view for 16-bit floats. XLA:CPU has no
    bfloat16 dynamic slice: it converts the *whole* operand to float32 and, the operand
    being loop-invariant, hoists that copy out of the loop (a float32 copy of K, V or
    every kept layer). Slicing the bits is exact and lets only the slice be converted."""
    if isinstance(x, Periodic):
        return x.rows_at(start, size, axis)
    if is_16bit_float(x):
        return _via_bits(lambda t, s: jax.lax.dynamic_slice_in_dim(t, s, size, axis), x, start)
    return jax.lax.dynamic_slice_in_dim(x, start, size, axis)


def slice_rows(x, start: int, stop: int, axis: int) -> jax.Array:
    """`lax.slice_in_dim` (static bounds) of an array or a `Periodic` one."""
    if isinstance(x, Periodic):
        return x.rows_at(start, stop - start, axis)
    return jax.lax.slice_in_dim(x, start, stop, axis=axis)


@jax.tree_util.register_pytree_node_class
class Periodic:
    """An array [B, n, ...] whose rows along axis 1 repeat every `period` rows, held as one
    period [B, period, ...]: the RoPE tables of a sequence of frames (every frame has the
    same positions). Tiled to the whole sequence they are 2 x 266 MB at 1000 frames of
    VGGT-1B and sat at the forward's peak; the chunk loops (`dynamic_slice`,
    `slice_rows`) take a chunk's rows from the period (row i is row i mod period), and
    `whole` tiles it where a loop runs in one chunk."""

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


@jax.tree_util.register_pytree_node_class
class Bits16:
    """A 16-bit float buffer held as its uint16 bits, for buffers a loop slices.

    `dynamic_slice` above views a 16-bit operand as bits at the slice; for a
    loop-invariant operand XLA hoists that view out of the loop, a copy of the whole
    buffer (8.5 GB for the kept layers' halves at 1000 frames of VGGT-1B, at the heads).
    Held as bits from the start, nothing is converted but what is written and read.

    Derivatives: bits have none, so the buffer carries a `shadow` of its float dtype
    whose value is never used: writes and reads send their tangents through it (custom
    JVPs). In a forward pass without derivatives the shadow is dead and XLA removes it."""

    def __init__(self, bits: jax.Array, shadow: jax.Array):
        self.bits, self.shadow = bits, shadow

    @classmethod
    def zeros_after(cls, shape: tuple[int, ...], dtype: Any, dep: jax.Array) -> "Bits16":
        return cls(zeros_after(shape, jnp.uint16, dep), zeros_after(shape, dtype, dep))

    @classmethod
    def of(cls, x: jax.Array) -> "Bits16":
        """x (16-bit floats) as its bits, x itself the shadow (its derivatives)."""
        return cls(jax.lax.bitcast_convert_type(jax.lax.stop_gradient(x), jnp.uint16), x)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.bits.shape

    @property
    def dtype(self):
        return self.shadow.dtype

    def update_index(self, x: jax.Array, index) -> "Bits16":
        """`lax.dynamic_update_index_in_dim(buffer, x, index, 0)` (x cast to the dtype)."""
        return Bits16(*_store_bits(self.bits, self.shadow, x.astype(self.dtype), index))

    def read(self, op, *index) -> jax.Array:
        """op(buffer, *index) (slicing ops only) in the float dtype."""
        return _load_bits(op, self.bits, self.shadow, *index)

    def tree_flatten(self):
        return (self.bits, self.shadow), None

    @classmethod
    def tree_unflatten(cls, _, children):
        return cls(*children)


def read_buffer(buf: "jax.Array | Bits16", op, *index) -> jax.Array:
    """op(buf, *index) for a plain array or a `Bits16` buffer; op a plain lax slicing op
    (for `Bits16` it is applied to the bits and to the tangents)."""
    return buf.read(op, *index) if isinstance(buf, Bits16) else op(buf, *index)


@jax.custom_jvp
def _store_bits(bits, shadow, x, index):
    return jax.lax.dynamic_update_index_in_dim(bits, jax.lax.bitcast_convert_type(x, jnp.uint16), index, 0), shadow


@_store_bits.defjvp
def _store_bits_jvp(primals, tangents):
    bits, shadow, x, index = primals
    _, shadow_dot, x_dot, _ = tangents
    out = _store_bits(bits, shadow, x, index)
    no_tangent = np.zeros(bits.shape, dtype=jax.dtypes.float0)
    return out, (no_tangent, jax.lax.dynamic_update_index_in_dim(shadow_dot, x_dot.astype(shadow.dtype), index, 0))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _load_bits(op, bits, shadow, *index):
    return jax.lax.bitcast_convert_type(op(bits, *index), shadow.dtype)


@_load_bits.defjvp
def _load_bits_jvp(op, primals, tangents):
    bits, shadow, *index = primals
    return _load_bits(op, bits, shadow, *index), op(tangents[1], *index)


def take(x: jax.Array, idx: jax.Array, axis: int) -> jax.Array:
    """`jnp.take(x, idx, axis, mode="clip")`, through a uint16 view for 16-bit
    floats, for the same reason as `dynamic_slice` (XLA:CPU has no bfloat16 gather)."""
    if is_16bit_float(x):
        return _via_bits(lambda t, i: jnp.take(t, i, axis=axis, mode="clip"), x, idx)
    return jnp.take(x, idx, axis=axis, mode="clip")


def take_along(x: jax.Array, idx: jax.Array, axis: int) -> jax.Array:
    """`jnp.take_along_axis(x, idx, axis)` (indices in bounds, idx broadcast over x's
    trailing axes), through a uint16 view for 16-bit floats."""
    idx = idx.reshape(idx.shape + (1,) * (x.ndim - idx.ndim))
    if is_16bit_float(x):
        return _via_bits(lambda t, i: jnp.take_along_axis(t, i, axis=axis, mode="promise_in_bounds"), x, idx)
    return jnp.take_along_axis(x, idx, axis=axis, mode="promise_in_bounds")


def dynamic_index(x: jax.Array, index, axis: int = 0) -> jax.Array:
    """`lax.dynamic_index_in_dim(..., keepdims=False)` through `dynamic_slice`."""
    return jax.lax.squeeze(dynamic_slice(x, index, 1, axis), (axis,))


def zeros_after(shape: tuple[int, ...], dtype: Any, dep: jax.Array) -> jax.Array:
    """Zeros of `shape` made from `dep`, so that the buffer exists only from `dep` on. A
    constant zero buffer (a loop's output or accumulator) is shared between loops and
    hoisted to the start of the program by XLA, every one alive at once (gigabytes at
    1000 frames)."""
    seed = jax.lax.stop_gradient(dep).reshape(-1)[:1].astype(jnp.float32) * 0.0
    seed = jnp.where(jnp.isnan(seed), 0.0, seed)  # dep may hold inf or NaN
    return jnp.broadcast_to(seed.astype(dtype).reshape(()), shape)


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


def _sweep(fn, acc, inputs: tuple, n: int, axis: int, rows: int, multiple: int, reader=None,
           in_place: bool = False):
    """The chunk loop of `map_tokens`, `read_tokens` and `update_tokens`: `count` chunks
    of `rows` (`even_chunks`), chunk i written at min(i * rows, n - rows). Why not a loop
    plus a shorter tail chunk: the tail is a second update of the loop's result outside
    the loop, and XLA then copies the whole buffer (the residual stream, 4 GB at 1000
    frames of VGGT-1B) for each consumer of the result.

    Where the last chunk overlaps the one before (n not a multiple of rows): a new array
    (`in_place` False) takes the overlapped rows again, computed from the same inputs; an
    array updated in place (`in_place`, `update_tokens`) keeps them (masked), since they
    are already updated. Reading the written rows back is what an update in place must
    do, and what a new array must not: for a 16-bit array, XLA:CPU turns that read into a
    float32 round trip of the whole buffer and a copy of it in every step (arrays of
    0.5-1.6 GB at 1000 frames of VGGT-1B in bfloat16).

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


def fold_owned(step, x: jax.Array, acc, inputs: tuple, n: int, rows: int):
    """(x, acc) with acc = step(acc, x_chunk, *input_chunks) over chunks of `rows` tokens
    (axis 1) of x and the inputs, as `fold_tokens`, in a loop that owns x (each chunk of x
    written back unchanged, `_written_back`), for the reason given in `read_tokens`. The
    shorter tail only reads x."""
    count = n // rows

    def body(i, carry):
        xs, a = carry
        xc = dynamic_slice(xs, i * rows, rows, 1)
        a = step(a, xc, *[dynamic_slice(t, i * rows, rows, 1) for t in inputs])
        return jax.lax.dynamic_update_slice_in_dim(xs, _written_back(xc, a), i * rows, 1), a

    x, acc = jax.lax.fori_loop(0, count, body, (x, acc))
    if count * rows < n:
        acc = step(acc, *[slice_rows(t, count * rows, n, 1) for t in (x, *inputs)])
    return x, acc


def after(x: jax.Array, dep) -> jax.Array:
    """x, unchanged, made to wait for `dep` (any pytree): x + a zero made from each of its
    leaves (exact; the add fuses into x's consumers). XLA orders ops by data dependency
    only (`lax.optimization_barrier` does not order them on CPU)."""
    for leaf in jax.tree.leaves(dep):
        x = x + zeros_after((), x.dtype, leaf)
    return x


def _written_back(xc: jax.Array, made_from) -> jax.Array:
    """x's chunk, unchanged, to write back into the x a loop owns: made from the loop's
    results (`after`), so that XLA cannot drop the write as a no-op."""
    return after(xc, made_from)


def _zero_outputs(fn, chunk_inputs: list, n: int, axis: int, dep: jax.Array):
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
    outs = _zero_outputs(fn, [dynamic_slice(t, 0, size, axis) for t in inputs], n, axis,
                         inputs[0] if dep is None else dep)
    return _sweep(lambda _, *c: fn(*c), outs, inputs, n, axis, rows, multiple)


def read_tokens(fn, x: jax.Array, inputs: tuple = (), axis: int = 1, rows: int | None = None,
                bytes_per_row: int = 0, multiple: int = 8, dep: jax.Array | None = None):
    """(x, fn(x_chunk, *input_chunks) stitched as in `map_tokens`), where the loop also
    owns x: each chunk of x is written back unchanged. A loop that only reads x passes it
    through, and XLA then copies x for the next loop that updates it in place (4 GB per
    layer at 1000 frames of VGGT-1B); owning it keeps one buffer from loop to loop.
    dep: the outputs are made after this value (default x), as in `map_tokens`."""
    n = x.shape[axis]
    rows = row_chunks(n, bytes_per_row, multiple=multiple) if rows is None else rows
    if rows >= n:
        return x, fn(x, *map(whole, inputs))
    _, size = even_chunks(n, rows, multiple)
    outs = _zero_outputs(fn, [dynamic_slice(t, 0, size, axis) for t in (x, *inputs)], n, axis,
                         x if dep is None else dep)

    def both(xc, *c):
        out = fn(xc, *c)
        return _written_back(xc, out), out

    return _sweep(both, (x, outs), inputs, n, axis, rows, multiple, lambda a: a[0])


def update_tokens(fn, x: jax.Array, inputs: tuple = (), axis: int = 1, rows: int | None = None,
                  bytes_per_row: int = 0, multiple: int = 8) -> jax.Array:
    """x with every chunk of `rows` tokens along `axis` replaced by `fn(x_chunk,
    *input_chunks)` (same shape and dtype), in place: the residual stream is updated
    without a second copy (x's chunk is read from the loop's own buffer)."""
    n = x.shape[axis]
    rows = row_chunks(n, bytes_per_row, multiple=multiple) if rows is None else rows
    if rows >= n:
        return fn(x, *map(whole, inputs))
    return _sweep(fn, x, inputs, n, axis, rows, multiple, lambda a: a, in_place=True)
