"""Fused attention kernels (`jax.nn.dot_product_attention`: cuDNN's flash kernel, or its
plain XLA form), which take no per-key bias: the bias is folded into the operands.

    softmax(q k^T * scale + bias) v = softmax(q' k'^T * scale) v'[..., :Dv]
    q' = [q, 1.., 0..], k' = [k, bias / scale, 0..], v' = [v, 0..]

(two bias columns hi + lo in 16-bit dtypes); the head dimension is zero-padded to a
multiple of 8 for cuDNN (D = 64 + the bias column would be 65).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# cuDNN's fused attention needs a head dimension that is a multiple of 8, at most 128.
CUDNN_HEAD_MULTIPLE = 8
CUDNN_MAX_HEAD_DIM = 128


def bias_columns(key_bias: jax.Array, dtype: Any) -> jax.Array:
    """A float32 key bias [B, Nk] as K columns [B, Nk, c] in `dtype`: one column in
    float32; in a 16-bit dtype a pair (hi, lo) whose sum is the bias to ~2^-16 relative.
    One bfloat16 column keeps 8 significant bits: the folded log g / scale of a group of
    100 (~37 at D = 64) would be rounded by up to 0.125, 0.016 in the logit, up to 1.6%
    of the group's weight."""
    dtype = jnp.dtype(dtype)
    if not (dtype.itemsize == 2 and jnp.issubdtype(dtype, jnp.floating)):
        return key_bias.astype(dtype)[..., None]
    hi = key_bias.astype(dtype)
    lo = (key_bias - hi.astype(jnp.float32)).astype(dtype)
    return jnp.stack([hi, lo], axis=-1)


def fold_key_bias(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                  multiple: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Fold an additive per-key bias into the operands and pad the head dimension:

        softmax(q k^T * scale + bias) v = softmax(q' k'^T * scale) v'[..., :Dv]
        q' = [q, 1.., 0..], k' = [k, bias / scale, 0..], v' = [v, 0..]

    (`bias_columns`: one bias column, or a hi/lo pair in 16-bit dtypes). q [B, Nq, H, D],
    k/v [B, Nk, H, D], key_bias [B, Nk] or None; every result has the head dimension
    (D + the bias columns, or Dv if larger) rounded up to a multiple of `multiple`."""
    if key_bias is not None:
        b, nk, h, _ = k.shape
        cols = bias_columns(key_bias.astype(jnp.float32) / np.float32(scale), k.dtype)  # [B, Nk, c]
        q = jnp.concatenate([q, jnp.ones(q.shape[:-1] + cols.shape[-1:], q.dtype)], axis=-1)
        k = jnp.concatenate([k, jnp.broadcast_to(cols[:, :, None, :], (b, nk, h, cols.shape[-1]))], axis=-1)
    dp = int(math.ceil(max(q.shape[-1], v.shape[-1]) / multiple) * multiple)

    def pad(x):
        return jnp.pad(x, ((0, 0), (0, 0), (0, 0), (0, dp - x.shape[-1])))

    return pad(q), pad(k), pad(v)


def fused_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                    implementation: str) -> jax.Array:
    """`jax.nn.dot_product_attention` with the key bias [B, Nk] (float32, or None) folded
    in: implementation "cudnn" (flash, head dims padded to CUDNN_HEAD_MULTIPLE) or "xla"
    (forms all logits). q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv] ->
    [B, Nq, H, Dv] in q's dtype."""
    dv = v.shape[-1]
    multiple = CUDNN_HEAD_MULTIPLE if implementation == "cudnn" else 1
    qf, kf, vf = fold_key_bias(q, k, v, key_bias, scale, multiple)
    if implementation == "cudnn" and qf.shape[-1] > CUDNN_MAX_HEAD_DIM:
        raise ValueError(f"cuDNN attention takes head dims up to {CUDNN_MAX_HEAD_DIM}; got {qf.shape[-1]}")
    out = jax.nn.dot_product_attention(qf, kf, vf, scale=scale, implementation=implementation)
    return out[..., :dv].astype(q.dtype)
