"""The one attention op of the model: every attention (frame, global, compressed with the
size bias, DINO, camera trunk, tracker) calls `attention`.

    out = attention(q, k, v)                       # softmax(q k^T / sqrt(D)) v
    out = attention(q, k, v, key_bias=log_g)       # + an additive bias per key [B, Nk]

It picks its kernel by name (`implementation`), like MaxText's attention op, each
kernel a module of `ops/kernels/`:

  "blocked"  `kernels/blocked.py` (the default, but for half precision on GPU): one
             (batch, head) pair and a cache-sized block of query rows at a time; memory
             bounded whatever the number of keys and the dtype.
  "cudnn"    `kernels/fused.py` (the default for bfloat16/float16 on GPU): cuDNN's flash
             kernel, the key bias folded into the operands; "xla" is its plain XLA form
             (forms all logits: for checks, not long sequences).

Ring attention (keys split over devices) is `ops/ring.py`, over the blocked kernel.

Precision: q, k, v in the compute dtype (float32 or bfloat16); logits, softmax
statistics and the value accumulation in float32; the result in q's dtype.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.kernels import blocked
from rvggt_jax.ops.kernels.blocked import blocked_attention
from rvggt_jax.ops.kernels.fused import fused_attention

IMPLEMENTATIONS = ("blocked", "xla", "cudnn")

# A key bias this negative removes the key: exp(NEG_BIAS - max) is exactly 0 in float32,
# and, being finite, a row whose keys are all removed can never turn into NaN.
NEG_BIAS = -1.0e4


def default_implementation(dtype: Any = jnp.float32) -> str:
    """"cudnn" for bfloat16/float16 operands on a GPU, else "blocked" (cuDNN's fused
    kernel takes no float32; the blocked kernel keeps float32 memory bounded anywhere)."""
    half = jnp.dtype(dtype) in (jnp.dtype(jnp.bfloat16), jnp.dtype(jnp.float16))
    return "cudnn" if half and jax.default_backend() == "gpu" else "blocked"


def attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None = None, *,
              scale: float | None = None, implementation: str | None = None,
              block_bytes: int | None = None) -> jax.Array:
    """softmax(q k^T * scale + key_bias) v over tokens.

    q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv]; key_bias None or [B, Nk] (added
    to every query's logits; NEG_BIAS removes a key). Returns [B, Nq, H, Dv] in q's
    dtype. `scale` defaults to 1/sqrt(D); `implementation` to `default_implementation()`.
    """
    if implementation is None:
        implementation = default_implementation(q.dtype)
    if implementation not in IMPLEMENTATIONS:
        raise ValueError(f"attention implementation must be one of {IMPLEMENTATIONS}; got {implementation!r}")
    if q.ndim != 4 or k.ndim != 4 or v.ndim != 4:
        raise ValueError(f"attention takes [B, N, H, D] operands; got {q.shape}, {k.shape}, {v.shape}")
    b, nq, h, d = q.shape
    if k.shape[:3] != (b, k.shape[1], h) or v.shape[:3] != k.shape[:3] or k.shape[-1] != d:
        raise ValueError(f"attention operands disagree: q {q.shape}, k {k.shape}, v {v.shape}")
    if key_bias is not None and key_bias.shape != (b, k.shape[1]):
        raise ValueError(f"key_bias must be [B, Nk] = {(b, k.shape[1])}; got {key_bias.shape}")
    scale = 1.0 / math.sqrt(d) if scale is None else float(scale)
    bias32 = None if key_bias is None else key_bias.astype(jnp.float32)

    if implementation == "blocked":
        block_bytes = blocked.LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes
        return blocked_attention(q, k, v, bias32, scale, block_bytes)[0].astype(q.dtype)
    return fused_attention(q, k, v, bias32, scale, implementation)


def log_sizes(sizes: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """The size bias log g [B, Nk] (float32): log of the group sizes, NEG_BIAS for empty
    slots (g = 0)."""
    lg = jnp.log(jnp.maximum(sizes.astype(jnp.float32), 1.0))
    if valid is not None:
        lg = jnp.where(valid, lg, np.float32(NEG_BIAS))
    return lg
