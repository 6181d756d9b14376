"""Values computed from other values so that XLA schedules them after those.

XLA orders operations by data dependency only: a constant buffer (a loop's zero output or
accumulator) is allocated at the program start and shared between loops, every one alive
at once, and an op whose inputs exist early runs early. Making a value from another one
places it. Where this mattered, and what it saved: docs/memory_layout.md.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

# The name of `with_dependency`'s zeros: a `jax.checkpoint` keeps these scalars
# (`model.remat`) rather than recompute them from the arrays they order after (a whole
# kept-layer buffer per aggregator layer, else).
ORDER_NAME = "rvggt_order"


def zeros_from(shape: tuple[int, ...], dtype: Any, dep: jax.Array) -> jax.Array:
    """Zeros of `shape` and `dtype` computed from `dep` (0 * one element of it), so that
    the buffer exists only from `dep` on: XLA shares a constant zero buffer between loops
    and allocates it at the program start (docs/memory_layout.md)."""
    seed = jax.lax.stop_gradient(dep).reshape(-1)[:1].astype(jnp.float32) * 0.0
    seed = jnp.where(jnp.isnan(seed), 0.0, seed)  # dep may hold inf or NaN
    return jnp.broadcast_to(seed.astype(dtype).reshape(()), shape)


def with_dependency(x: jax.Array, dep) -> jax.Array:
    """x, unchanged, computed from each leaf of `dep` too (x + a zero made from it: exact;
    the add fuses into x's consumers): XLA orders ops by data dependency only, and
    `lax.optimization_barrier` does not order them on CPU. Each zero is named ORDER_NAME:
    a checkpoint whose backward pass recomputes x keeps the zero, not `dep`."""
    for leaf in jax.tree.leaves(dep):
        x = x + checkpoint_name(zeros_from((), x.dtype, leaf), ORDER_NAME)
    return x
