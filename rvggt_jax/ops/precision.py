"""The precision of float32 matmuls and convolutions inside a forward.

JAX resolves a matmul's precision when it is traced (`lax.dot_general` and
`lax.conv_general_dilated` read `jax_default_matmul_precision` when given none), so one
scope around the traced forward reaches every float32 product in it. Their transposes in
a gradient keep the precision their forward was traced with; a custom VJP's backward is
traced later, outside the scope, so it carries its forward's precision itself (the blocked
attention's: `kernels/blocked.py`). A CPU computes float32 products in full at every
precision; an NVIDIA GPU's "default" is TF32 and a TPU's one bf16 pass, which is why
`VGGTConfig.dot_precision` is "highest" for float32 configs.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import jax


@contextlib.contextmanager
def precision_scope(precision: str | None) -> Iterator[None]:
    """Every float32 matmul traced inside runs at `precision` ("default", "high",
    "highest"); None leaves JAX's own setting as it is."""
    if precision is None:
        yield
        return
    with jax.default_matmul_precision(precision):
        yield
