"""The cache-blocked attention kernel (the CPU kernel, and the one every float32 attention
takes): one (batch, head) pair and a cache-sized block of query rows at a time, logits in
float32, normalised after the value product, the key bias added to each logits block.
It also returns the log-sum-exp of every query's logits (ring attention folds partial
results with it).

Working memory does not grow with the number of keys beyond K and V themselves (and
their head-major copies): one [rows, Nk] logits block per step, rows chosen so that the
block fits LOGITS_BLOCK_BYTES.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from rvggt_jax.ops.bits import Bits16, is_16bit_float, read_buffer
from rvggt_jax.ops.chunks import dynamic_index
from rvggt_jax.ops.ordering import zeros_from

# Bytes of one logits block: a block that stays in L2/L3 and gives the value matmul
# hundreds of rows (measurements: docs/benchmarks.md).
LOGITS_BLOCK_BYTES = 24 * 2**20

def query_blocks(nq: int, nk: int, itemsize: int = 4, block_bytes: int | None = None) -> tuple[int, int]:
    """(number of query blocks, rows per block) for one (batch, head) pair: the fewest
    blocks whose [rows, Nk] logits fit `block_bytes` (default LOGITS_BLOCK_BYTES), rows
    rounded up to a multiple of 8 so that padding stays under 8 rows per block."""
    block_bytes = LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes
    max_rows = max(8, block_bytes // (nk * itemsize))
    if nq <= max_rows:
        return 1, nq
    rows = 8 * math.ceil(math.ceil(nq / math.ceil(nq / max_rows)) / 8)
    return math.ceil(nq / rows), rows


def softmax_attend(q: jax.Array, kt: jax.Array, v: jax.Array, bias: jax.Array | None
                    ) -> tuple[jax.Array, jax.Array]:
    """q [..., n, D] (pre-scaled), kt [..., D, Nk], v [..., Nk, Dv], bias [..., 1, Nk] or
    None -> ([..., n, Dv], the log-sum-exp of the logits [..., n]) in float32.
    Normalises after the value product: n*Dv divisions instead of n*Nk."""
    logits = jnp.matmul(q, kt, preferred_element_type=jnp.float32)
    if bias is not None:
        logits = logits + bias
    m = jax.lax.stop_gradient(logits.max(axis=-1, keepdims=True))
    e = jnp.exp(logits - m)
    out = jnp.matmul(e.astype(v.dtype), v, preferred_element_type=jnp.float32)
    total = e.sum(axis=-1, keepdims=True)
    return out / total, (m + jnp.log(total))[..., 0]


def blocked_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
             block_bytes: int, out_dtype: Any = None, *, bits: bool = True) -> tuple[jax.Array, jax.Array]:
    """The cache-blocked kernel. q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv], key_bias
    [B, Nk] float32 or None -> ([B, Nq, H, Dv] (float32 when in one block, else
    `out_dtype`, default q's), log-sum-exp of the logits [B, Nq, H] float32).
    bits: hold 16-bit operands as `Bits16` in the loop (XLA:CPU's workaround; the attention
    op passes False for the programs it compiles for other platforms)."""
    b, nq, h, d = q.shape
    nk, dv = k.shape[1], v.shape[-1]
    qt = (q * jnp.asarray(scale, q.dtype)).transpose(0, 2, 1, 3)  # [B, H, Nq, D]
    kt = k.transpose(0, 2, 3, 1)  # [B, H, D, Nk]
    vt = v.transpose(0, 2, 1, 3)  # [B, H, Nk, Dv]
    bias = None if key_bias is None else key_bias[:, None, None, :]  # [B, 1, 1, Nk]
    if b * h * nq * nk * 4 <= block_bytes:
        out, lse = softmax_attend(qt, kt, vt, bias)
        return out.transpose(0, 2, 1, 3), lse.transpose(0, 2, 1)

    n, rows = query_blocks(nq, nk, 4, block_bytes)
    qb = jnp.pad(qt, ((0, 0), (0, 0), (0, n * rows - nq), (0, 0))).reshape(b * h * n, rows, d)
    kt, vt = kt.reshape(b * h, d, nk), vt.reshape(b * h, nk, dv)
    # 16-bit operands as bits from the start (a bit view made in the loop is hoisted out
    # of it as a copy of the operand)
    qb, kt, vt = (Bits16.of(t) if bits and is_16bit_float(t) else t for t in (qb, kt, vt))

    def index(t, i):
        return read_buffer(t, lambda a, j: jax.lax.dynamic_index_in_dim(a, j, 0, keepdims=False), i)

    def body(i, acc):
        out, lse = acc
        pair = i // n  # (batch, head) pair of this block
        kb, vb = index(kt, pair), index(vt, pair)
        bb = None if bias is None else dynamic_index(bias[:, 0], pair // h)
        res, res_lse = softmax_attend(index(qb, i), kb, vb, bb)
        return (jax.lax.dynamic_update_index_in_dim(out, res.astype(out.dtype), i, 0),
                jax.lax.dynamic_update_index_in_dim(lse, res_lse, i, 0))

    # (the output buffer made from q: a constant one would live from the program start)
    out_dtype = q.dtype if out_dtype is None else out_dtype
    init = zeros_from((b * h * n, rows, dv), out_dtype, q)
    out, lse = jax.lax.fori_loop(0, b * h * n, body, (init, zeros_from((b * h * n, rows), jnp.float32, init)))
    return (out.reshape(b, h, n * rows, dv)[:, :, :nq].transpose(0, 2, 1, 3),
            lse.reshape(b, h, n * rows)[:, :, :nq].transpose(0, 2, 1))
