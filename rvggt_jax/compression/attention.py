"""Size-biased attention with the bias folded into the operands.

    softmax(Q K^T / sqrt(d) + log g) V
      = softmax(Q' K'^T / sqrt(d)) V'[..., :d]
    with Q' = [Q, 1, 0...], K' = [K, sqrt(d) log g, 0...], V' = [V, 0, 0...]

The head dimension d + 1 is zero-padded to a multiple of `pad_multiple` (16 gives the
GPU flash-attention size 80 for d = 64). Empty K/V slots get g = 0, written as a large
negative *finite* log (NEG_LOG), never -inf: their weight underflows to exactly 0 and a
row can never become NaN.

The core attention runs over chunks of queries (`lax.map`), normalising after the
P V product: the [chunk, N_k] logits stay in cache, and no [N_q, N_k] matrix is
materialised at once.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

# log(g) of an empty slot: exp(NEG_LOG - max) is exactly 0 in float32.
NEG_LOG = -1.0e4


def _attend(q: jax.Array, k: jax.Array, v: jax.Array) -> jax.Array:
    """Head-major q [B, H, n, D] (already scaled), k [B, H, Nk, D], v [B, H, Nk, Dv] ->
    [B, H, n, Dv]."""
    logits = jnp.einsum("bhqd,bhkd->bhqk", q, k)
    m = jax.lax.stop_gradient(jnp.max(logits, axis=-1, keepdims=True))
    e = jnp.exp(logits - m)
    return jnp.einsum("bhqk,bhkd->bhqd", e, v) / jnp.sum(e, axis=-1, keepdims=True)


def core_attention(q: jax.Array, k: jax.Array, v: jax.Array, scale: float, chunk: int = 0) -> jax.Array:
    """softmax(q k^T * scale) v over chunks of `chunk` queries (0: one chunk).

    q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv] -> [B, Nq, H, Dv]. The operands are
    made head-major once, outside the chunk loop."""
    b, nq, h, _ = q.shape
    qt = jnp.transpose(q * jnp.asarray(scale, q.dtype), (0, 2, 1, 3))
    kt = jnp.transpose(k, (0, 2, 1, 3))
    vt = jnp.transpose(v, (0, 2, 1, 3))
    if chunk <= 0 or nq <= chunk:
        return jnp.transpose(_attend(qt, kt, vt), (0, 2, 1, 3))
    n_chunks = -(-nq // chunk)
    qp = jnp.pad(qt, ((0, 0), (0, 0), (0, n_chunks * chunk - nq), (0, 0)))
    qp = jnp.moveaxis(qp.reshape(b, h, n_chunks, chunk, qt.shape[-1]), 2, 0)
    out = jax.lax.map(lambda qc: _attend(qc, kt, vt), qp)  # [n_chunks, B, H, chunk, Dv]
    out = jnp.moveaxis(out, 0, 2).reshape(b, h, n_chunks * chunk, vt.shape[-1])[:, :, :nq]
    return jnp.transpose(out, (0, 2, 1, 3))


def fold_size_bias(q: jax.Array, k: jax.Array, v: jax.Array, log_g: jax.Array,
                   pad_multiple: int = 1) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Q' = [Q, 1, 0..], K' = [K, sqrt(d) log g, 0..], V' = [V, 0, 0..], head dim padded to a
    multiple of `pad_multiple`. q [B, Nq, H, d]; k, v [B, Nk, H, d]; log_g [B, Nk].
    With pad_multiple == 1, V is returned as it is (see below)."""
    d = q.shape[-1]
    dp = int(math.ceil((d + 1) / pad_multiple) * pad_multiple)
    extra = dp - d - 1
    b, nk, h, _ = k.shape
    col_q = jnp.ones(q.shape[:-1] + (1,), q.dtype)
    col_k = jnp.broadcast_to((math.sqrt(d) * log_g).astype(k.dtype)[:, :, None, None], (b, nk, h, 1))
    zq = jnp.zeros(q.shape[:-1] + (extra,), q.dtype)
    zk = jnp.zeros(k.shape[:-1] + (extra,), k.dtype)
    qf = jnp.concatenate([q, col_q, zq], axis=-1)
    kf = jnp.concatenate([k, col_k, zk], axis=-1)
    if pad_multiple == 1:
        # Our attention does not need equal Q/K and V head dims: V stays [.., d] (the
        # zero column of V' contributes nothing) and P V costs d, not d + 1.
        return qf, kf, v
    vf = jnp.concatenate([v, jnp.zeros(v.shape[:-1] + (1 + extra,), v.dtype)], axis=-1)
    return qf, kf, vf


def size_biased_attention(q: jax.Array, k: jax.Array, v: jax.Array, log_g: jax.Array | None,
                          pad_multiple: int = 1, chunk: int = 0) -> jax.Array:
    """softmax(q k^T / sqrt(d) + log_g) v with log_g [B, Nk] folded into an extra Q/K
    column (None: plain attention). q [B, Nq, H, d], k/v [B, Nk, H, d] -> [B, Nq, H, d]."""
    d = q.shape[-1]
    scale = 1.0 / math.sqrt(d)
    if log_g is None:
        return core_attention(q, k, v, scale, chunk)
    qf, kf, vf = fold_size_bias(q, k, v, log_g, pad_multiple)
    return core_attention(qf, kf, vf, scale, chunk)[..., :d]


def log_sizes(sizes: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """log g for valid slots, NEG_LOG for empty ones (g = 0)."""
    lg = jnp.log(jnp.maximum(sizes, 1.0))
    if valid is not None:
        lg = jnp.where(valid, lg, NEG_LOG)
    return lg
