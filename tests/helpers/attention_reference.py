"""The attention references of the attention tests: float64 numpy (values), and plain
float32 jnp (whose autodiff the kernels' backwards are checked against)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np


def reference_attention(q, k, v, bias=None):
    """softmax(q k^T / sqrt(d) + bias) v in float64 numpy, upstream's [B, H, N, D] layout."""
    q, k, v = (np.asarray(a, np.float64).transpose(0, 2, 1, 3) for a in (q, k, v))
    logits = q @ k.transpose(0, 1, 3, 2) / math.sqrt(q.shape[-1])
    if bias is not None:
        logits = logits + np.asarray(bias, np.float64)
    p = np.exp(logits - logits.max(-1, keepdims=True))
    return ((p / p.sum(-1, keepdims=True)) @ v).transpose(0, 2, 1, 3)


def differentiable_reference(q, k, v, bias=None, scale=None):
    """(softmax(q k^T * scale + bias) v [B, Nq, H, Dv], log-sum-exp [B, Nq, H]) in
    float32 plain jnp: the forms whose autodiff the kernel's backward must equal."""
    scale = 1.0 / math.sqrt(q.shape[-1]) if scale is None else scale
    hp = jax.lax.Precision.HIGHEST
    s = jnp.einsum("bqhd,bkhd->bhqk", q.astype(jnp.float32), k.astype(jnp.float32), precision=hp) * scale
    if bias is not None:
        s = s + bias[:, None, None, :]
    out = jnp.einsum("bhqk,bkhe->bqhe", jax.nn.softmax(s, axis=-1), v.astype(jnp.float32), precision=hp)
    return out, jax.nn.logsumexp(s, axis=-1).transpose(0, 2, 1)


def rel(a, b) -> float:
    """max |a - b| / max |b| (float64)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
