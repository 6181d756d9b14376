"""Where a value is computed: the model's one interface to the compiler's scheduling.

The model says what it needs by intent, and the reasons live here and in
docs/memory_layout.md:

    ordered_after(x, dep)        x, unchanged, computed after every leaf of dep exists
    zeros_after(shape, dtype, dep)  zeros that exist only from dep on
    materialize(values)          values computed here, whole, as they are
    relu_unwritten(x, dep)       jax.nn.relu(x) whose zero is never written out as a map

Why a model needs to say this at all: XLA orders operations by data dependency only. A
constant buffer (a loop's zero output or accumulator) is allocated at the program start
and shared between loops, every one alive at once, and an op whose inputs exist early runs
early. Making a value from another one places it: the buffer exists from that value on.
And XLA fuses a cheap value into each of its consumers, recomputing it, unless a barrier
says it is computed once. Each use in the model is a measured saving in memory or time
(docs/memory_layout.md); every one is exact: the values are those without it, bit for bit.
"""

from __future__ import annotations

from typing import Any, TypeVar

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

T = TypeVar("T")

# The name of `ordered_after`'s zeros: a `jax.checkpoint` keeps these scalars
# (`model.remat`) rather than recompute them from the arrays they order after (a whole
# kept-layer buffer per aggregator layer, else).
ORDER_NAME = "rvggt_order"


def zeros_after(shape: tuple[int, ...], dtype: Any, dep: jax.Array) -> jax.Array:
    """Zeros of `shape` and `dtype` computed from `dep` (0 * one element of it), so that
    the buffer exists only from `dep` on: XLA shares a constant zero buffer between loops
    and allocates it at the program start (docs/memory_layout.md)."""
    seed = jax.lax.stop_gradient(dep).reshape(-1)[:1].astype(jnp.float32) * 0.0
    seed = jnp.where(jnp.isnan(seed), 0.0, seed)  # dep may hold inf or NaN
    return jnp.broadcast_to(seed.astype(dtype).reshape(()), shape)


def ordered_after(x: jax.Array, dep) -> jax.Array:
    """x, unchanged, computed from each leaf of `dep` too (x + a zero made from it: exact;
    the add fuses into x's consumers): XLA orders ops by data dependency only, and
    `lax.optimization_barrier` does not order them on CPU. Each zero is named ORDER_NAME:
    a checkpoint whose backward pass recomputes x keeps the zero, not `dep`."""
    for leaf in jax.tree.leaves(dep):
        x = x + checkpoint_name(zeros_after((), x.dtype, leaf), ORDER_NAME)
    return x


def materialize(values: T) -> T:
    """`values` (any pytree), computed here and whole: not fused into their consumers (each
    of which would recompute them) and not split across them (`lax.optimization_barrier`).
    Exact: the values are unchanged."""
    return jax.lax.optimization_barrier(values)


def relu_unwritten(x: jax.Array, dep: jax.Array) -> jax.Array:
    """jax.nn.relu(x) for x [..., I] (the same values and gradient), taken against a zero
    vector [I] made from `dep` rather than a scalar constant: XLA:CPU's YNNPACK fusion of a
    convolution, the ReLU and a reduction writes a scalar's broadcast out as a whole map of
    zeros (one [frames, H, W, I] map per frame group of a DPT head), a vector it broadcasts
    itself (docs/memory_layout.md)."""
    return _relu_against(x, zeros_after(x.shape[-1:], x.dtype, dep))


@jax.custom_jvp
def _relu_against(x: jax.Array, zero: jax.Array) -> jax.Array:
    return jnp.maximum(x, zero)


@_relu_against.defjvp
def _relu_against_jvp(primals, tangents):
    x, zero = primals
    return _relu_against(x, zero), jnp.where(x > zero, tangents[0], jnp.zeros_like(tangents[0]))
