"""Ring attention: the attention of this device's queries to keys split over devices,
the key shares passed around the ring of devices, partial results folded by their
log-sum-exp (the online softmax of flash attention, across devices)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from rvggt_jax.ops.attention import attention_with_lse
from rvggt_jax.ops.shards import FrameShards


def ring_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, shards: FrameShards,
                   extra: tuple = (), *, scale: float | None = None,
                   block_bytes: int | None = None, implementation: str = "auto") -> jax.Array:
    """`attention` of this device's queries to keys split over devices, without ever
    holding more than two devices' keys: q [B, Nq, H, D]; k, v [B, Nk, H, D] and
    key_bias [B, Nk] (or None) this device's share of the keys; `extra`: (k, v, bias)
    triples every device attends to as they are (replicated keys); `implementation`: the
    kernel (`ops.attention`) of each share's attention. Returns
    [B, Nq, H, Dv] in q's dtype.

    The shares travel around the devices (`FrameShards.ring_shift`, a collective permute
    per step); each step's partial attention, with its log-sum-exp, is folded into a
    running float32 result (the online softmax of flash attention, across devices). On
    one device: the own keys, then the extra ones, folded the same way."""
    d = q.shape[-1]
    scale = 1.0 / math.sqrt(d) if scale is None else float(scale)

    def part(kk, vv, bb):
        return attention_with_lse(q, kk, vv, bb, scale, block_bytes, jnp.float32, implementation=implementation)

    def fold(acc, new):
        (o, lse), (o2, lse2) = acc, new
        top = jnp.logaddexp(lse, lse2)
        return (o * jnp.exp(lse - top)[..., None] + o2.astype(jnp.float32) * jnp.exp(lse2 - top)[..., None], top)

    def step(_, carry):
        acc, shard = carry
        shard = shards.ring_shift(shard)
        return fold(acc, part(*shard)), shard

    acc = part(k, v, key_bias)
    acc = tuple(a.astype(jnp.float32) for a in acc)
    if shards.sharded:
        acc, _ = jax.lax.fori_loop(1, shards.devices, step, (acc, (k, v, key_bias)))
    for ek, ev, eb in extra:
        acc = fold(acc, part(ek, ev, eb))
    return acc[0].astype(q.dtype)
