"""Query points for tracking, as users write them, and the public `rvggt_forward` that
accepts them.

A query point is a pixel `(x, y)` in frame 0 of the network input (the preprocessed
image, e.g. 518 x 392, not the original photo; `ImageInfo` maps original pixels there):
x to the right, y down, continuous coordinates. Shape `[N, 2]` (the same points for
every batch element) or `[B, N, 2]`. Lists, tuples, NumPy and JAX arrays of ints or
floats are accepted (as float32); anything else is an `InputError` saying what was
given. `rvggt_jax.rvggt_forward` applies this before the model's own checks, inside
`jax.jit` too (a list passed to a jitted function arrives as a nested list of scalars).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from rvggt_jax.model import InputError
from rvggt_jax.model import rvggt_forward as _model_forward

__all__ = ["as_query_points", "rvggt_forward"]

_HELP = "query_points are pixel (x, y) in frame 0 of the network input, shape [N, 2] or [B, N, 2]"

def as_query_points(query_points: Any) -> jnp.ndarray:
    """`query_points` (list / tuple / NumPy / JAX, ints or floats) -> float32 array
    [N, 2] or [B, N, 2]. Raises `InputError` naming the problem."""
    if isinstance(query_points, (str, bytes, dict, set)) or query_points is None:
        raise InputError(f"{_HELP}; got a {type(query_points).__name__}")
    try:
        arr = jnp.asarray(query_points)
    except (TypeError, ValueError) as e:
        raise InputError(f"{_HELP}; cannot read a {type(query_points).__name__} as numbers "
                         f"({' '.join(str(e).split())[:200]})") from None
    if arr.ndim not in (2, 3) or arr.shape[-1] != 2:
        raise InputError(f"{_HELP}; got shape {tuple(arr.shape)}")
    if not (jnp.issubdtype(arr.dtype, jnp.floating) or jnp.issubdtype(arr.dtype, jnp.integer)) \
            or arr.dtype == jnp.bool_:
        raise InputError(f"{_HELP}; got dtype {arr.dtype}")
    return arr.astype(jnp.float32)

def rvggt_forward(params, images, config, query_points=None) -> dict[str, Any]:
    """`rvggt_jax.model.rvggt_forward` (see there for every input and output shape)
    with `query_points` given as any array-like (see `as_query_points`)."""
    if query_points is not None:
        query_points = as_query_points(query_points)
    return _model_forward(params, images, config, query_points)

rvggt_forward.__doc__ += "\n\n" + (_model_forward.__doc__ or "")

