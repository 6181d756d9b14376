"""16-bit floats moved as their uint16 bits: the XLA:CPU workarounds, in one place.

XLA:CPU has no bfloat16 dynamic slice, gather or collective: it converts the whole
operand to float32 first (and, for a loop-invariant operand, hoists that copy out of the
loop), and moves a bfloat16 collective in float32. Slicing, gathering or moving the bits
is exact and converts only what is used. Why and what it saves: docs/memory_layout.md.

    on_cpu(cpu, other)        cpu() when compiling for a CPU, other() for any other platform
    as_bits(op, x, *index)    op (a slice, gather or move of x) applied to x's bits
    moved(op, x, *index)      as_bits for 16-bit floats compiled for a CPU, op itself otherwise
    HalfBuffer                    a 16-bit buffer held as bits (the kept layers, the blocked
                              kernel's K/V on a CPU)
    read_buffer(buf, op, ...) op on a plain array or a `HalfBuffer` buffer
    write_buffer(buf, op, x, index)  a dynamic update of either
    rounded(x, dtype)         float32 x rounded to a 16-bit dtype's precision, still float32

GPUs and TPUs slice, gather and move 16-bit floats natively, so the ops take the plain
form there (`on_cpu`: the choice is made when the program is lowered for its platform,
not from the host's default backend). The kept layers' buffer stays `HalfBuffer` on every
platform: its type is fixed when the program is traced, before the platform is known,
and a bit view costs nothing on an accelerator (it fuses into the slice reading it).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.ordering import zeros_after


def is_16bit_float(x: jax.Array) -> bool:
    return x.dtype.itemsize == 2 and jnp.issubdtype(x.dtype, jnp.floating)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def as_bits(op, x: jax.Array, *index) -> jax.Array:
    """`op(x, *index)` (a slice, gather or move of x: a linear map) on x's uint16 bits.
    The bitcast to integers has no derivative (JAX would silently give zero gradients
    through it), so the JVP applies `op` to the tangent directly, which reverse mode
    transposes (into a scatter-add / update of zeros)."""
    bits = op(jax.lax.bitcast_convert_type(x, jnp.uint16), *index)
    return jax.lax.bitcast_convert_type(bits, x.dtype)


@as_bits.defjvp
def _as_bits_jvp(op, primals, tangents):
    x, *index = primals
    return as_bits(op, x, *index), op(tangents[0], *index)


def on_cpu(cpu, other):
    """`cpu()` in a program compiled for a CPU, `other()` in one compiled for any other
    platform: `jax.lax.platform_dependent`, which lowers only the branch of the platform
    the program is lowered for (a program traced on a CPU host and compiled for a GPU
    takes `other`). Both are traced; their results must have the same types."""
    return jax.lax.platform_dependent(cpu=cpu, default=other)


def moved(op, x: jax.Array, *index) -> jax.Array:
    """`op(x, *index)` for an op that only moves x's values (a slice, gather, permute, a
    psum with one non-zero term): on x's bits when x is a 16-bit float compiled for a
    CPU (`as_bits`), the op itself on other platforms and for other dtypes."""
    if not is_16bit_float(x):
        return op(x, *index)
    return on_cpu(lambda: as_bits(op, x, *index), lambda: op(x, *index))


@jax.tree_util.register_pytree_node_class
class HalfBuffer:
    """A 16-bit float buffer held as its uint16 bits, for buffers a loop slices: a bit
    view made at the slice would be hoisted out of the loop as a copy of the whole buffer.

    Derivatives: bits have none, so the buffer carries a `shadow` of its float dtype
    whose value is never used: writes and reads send their tangents through it (custom
    JVPs). In a forward pass without derivatives the shadow is dead and XLA removes it."""

    def __init__(self, bits: jax.Array, shadow: jax.Array):
        self.bits, self.shadow = bits, shadow

    @classmethod
    def zeros_after(cls, shape: tuple[int, ...], dtype: Any, dep: jax.Array) -> "HalfBuffer":
        return cls(zeros_after(shape, jnp.uint16, dep), zeros_after(shape, dtype, dep))

    @classmethod
    def of(cls, x: jax.Array) -> "HalfBuffer":
        """x (16-bit floats) as its bits, x itself the shadow (its derivatives)."""
        return cls(jax.lax.bitcast_convert_type(jax.lax.stop_gradient(x), jnp.uint16), x)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.bits.shape

    @property
    def dtype(self):
        return self.shadow.dtype

    def update(self, op, x: jax.Array, index) -> "HalfBuffer":
        """op(buffer, x, index) (a lax dynamic update: linear in buffer and x), x cast to
        the dtype."""
        return HalfBuffer(*_store_bits(op, self.bits, self.shadow, x.astype(self.dtype), index))

    def update_index(self, x: jax.Array, index) -> "HalfBuffer":
        """`lax.dynamic_update_index_in_dim(buffer, x, index, 0)` (x cast to the dtype)."""
        return self.update(_update_index, x, index)

    def read(self, op, *index) -> jax.Array:
        """op(buffer, *index) (slicing ops only) in the float dtype."""
        return _load_bits(op, self.bits, self.shadow, *index)

    def tree_flatten(self):
        return (self.bits, self.shadow), None

    @classmethod
    def tree_unflatten(cls, _, children):
        return cls(*children)


def read_buffer(buf: "jax.Array | HalfBuffer", op, *index) -> jax.Array:
    """op(buf, *index) for a plain array or a `HalfBuffer` buffer; op a plain lax slicing op
    (for `HalfBuffer` it is applied to the bits and to the tangents)."""
    return buf.read(op, *index) if isinstance(buf, HalfBuffer) else op(buf, *index)


def write_buffer(buf: "jax.Array | HalfBuffer", op, x: jax.Array, index) -> "jax.Array | HalfBuffer":
    """op(buf, x, index) for a plain array or a `HalfBuffer` buffer, x cast to the buffer's
    dtype; op a lax dynamic update (for `HalfBuffer` applied to the bits and to the
    tangents)."""
    return buf.update(op, x, index) if isinstance(buf, HalfBuffer) else op(buf, x.astype(buf.dtype), index)


def _update_index(buf, x, index):
    return jax.lax.dynamic_update_index_in_dim(buf, x, index, 0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _store_bits(update, bits, shadow, x, index):
    return update(bits, jax.lax.bitcast_convert_type(x, jnp.uint16), index), shadow


@_store_bits.defjvp
def _store_bits_jvp(update, primals, tangents):
    bits, shadow, x, index = primals
    _, shadow_dot, x_dot, _ = tangents
    out = _store_bits(update, bits, shadow, x, index)
    no_tangent = np.zeros(bits.shape, dtype=jax.dtypes.float0)
    return out, (no_tangent, update(shadow_dot, x_dot.astype(shadow.dtype), index))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _load_bits(op, bits, shadow, *index):
    return jax.lax.bitcast_convert_type(op(bits, *index), shadow.dtype)


@_load_bits.defjvp
def _load_bits_jvp(op, primals, tangents):
    bits, shadow, *index = primals
    return _load_bits(op, bits, shadow, *index), op(tangents[1], *index)


def rounded(x: jax.Array, dtype) -> jax.Array:
    """float32 x rounded to `dtype`'s precision, still float32. bfloat16 by its bits
    (round to nearest even on the upper 16 bits): a cast would let XLA:TPU's bfloat16
    propagation turn the stream it slices into bfloat16 whole, a 2 GB copy at 1000
    frames (and another for its re-layout)."""
    if jnp.dtype(dtype) != jnp.dtype(jnp.bfloat16):
        return x.astype(dtype).astype(jnp.float32)
    bits = jax.lax.bitcast_convert_type(x.astype(jnp.float32), jnp.uint32)
    bits = (bits + jnp.uint32(0x7FFF) + ((bits >> 16) & 1)) & jnp.uint32(0xFFFF0000)
    return jnp.where(jnp.isnan(x), x, jax.lax.bitcast_convert_type(bits, jnp.float32))
