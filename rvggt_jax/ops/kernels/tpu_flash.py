"""The Pallas TPU flash attention kernel (`jax.experimental.pallas.ops.tpu.flash_attention`)
with the key bias folded into the operands, as for cuDNN (`fused.fold_key_bias`).

The kernel tiles sequences in blocks of 128 rows: queries and keys are padded to a
multiple of that, and padded keys are removed through the folded bias column (NEG_BIAS,
exactly 0 after the softmax), so a bias column is always present. The head dimension
(D + the bias columns) is padded to a multiple of 8; the kernel takes any head dimension
up to 128. It carries its own backward (flash attention's, blockwise: O(N d) memory).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from rvggt_jax.ops.kernels.fused import fold_key_bias

# the kernel's sequence block (its BlockSizes defaults) and largest unpadded head dim
BLOCK = 128
MAX_HEAD_DIM = 128
HEAD_MULTIPLE = 8


def tpu_flash_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                        neg_bias: float) -> jax.Array:
    """q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv], key_bias [B, Nk] float32 or
    None -> [B, Nq, H, Dv] in q's dtype; `neg_bias` is the bias that removes a key."""
    from jax.experimental.pallas.ops.tpu import flash_attention as pallas_flash

    b, nq, h, _ = q.shape
    nk, dv = k.shape[1], v.shape[-1]
    pq, pk = BLOCK * math.ceil(nq / BLOCK) - nq, BLOCK * math.ceil(nk / BLOCK) - nk
    bias = jnp.zeros((b, nk), jnp.float32) if key_bias is None else key_bias.astype(jnp.float32)
    bias = jnp.pad(bias, ((0, 0), (0, pk)), constant_values=neg_bias)

    def pad_rows(x, n):
        return jnp.pad(x, ((0, 0), (0, n), (0, 0), (0, 0)))

    qf, kf, vf = fold_key_bias(pad_rows(q, pq), pad_rows(k, pk), pad_rows(v, pk), bias, scale, HEAD_MULTIPLE)
    if qf.shape[-1] > MAX_HEAD_DIM:
        raise ValueError(f"the TPU flash kernel takes head dims up to {MAX_HEAD_DIM} (with the bias columns); "
                         f"got {qf.shape[-1]}")
    out = pallas_flash.flash_attention(*(x.transpose(0, 2, 1, 3) for x in (qf, kf, vf)), sm_scale=scale)
    return out.transpose(0, 2, 1, 3)[:, :nq, :, :dv].astype(q.dtype)
