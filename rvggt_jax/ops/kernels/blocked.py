"""The cache-blocked attention kernel (the CPU kernel, and the one every float32 attention
takes): one (batch, head) pair and a cache-sized block of query rows at a time, logits in
float32, normalised after the value product, the key bias added to each logits block.
It also returns the log-sum-exp of every query's logits (ring attention folds partial
results with it).

Working memory does not grow with the number of keys beyond K and V themselves (and
their head-major copies): one [rows, Nk] logits block per step, rows chosen so that the
block fits LOGITS_BLOCK_BYTES.

Reverse mode (`jax.custom_vjp`, flash attention's backward): the forward saves only q, k,
v, the key bias, the output and the log-sum-exp of every query's logits; the backward
walks the same query blocks, recomputes each block's softmax weights from q, k and the
saved log-sum-exp, and accumulates dq, dk, dv and the key bias's gradient (its column
sums of dS over heads and queries) block by block. Its memory is O(N d) plus a few
[rows, Nk] float32 blocks, where autodiff of the loop would keep every block's weights
(O(Nq Nk) per (batch, head) pair: ~70 GB per global layer of VGGT-1B at 24 frames).
The cotangent of the log-sum-exp output (ring attention folds partial results with it,
and differentiates through that fold) is taken too: d lse_i / d s_ij = P_ij.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from rvggt_jax.ops.bits import HalfBuffer, is_16bit_float, read_buffer
from rvggt_jax.ops.chunks import dynamic_index
from rvggt_jax.ops.ordering import zeros_after
from rvggt_jax.ops.precision import precision_scope

# Bytes of one logits block: a block that stays in L2/L3 and gives the value matmul
# hundreds of rows (measurements: docs/history/dense_forward.md, long_sequences.md, cpu_speed.md).
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


def logits_of(q: jax.Array, k: jax.Array) -> jax.Array:
    """q [..., n, D] @ k [..., Nk, D]^T -> [..., n, Nk] float32. Keys stay row-major: the
    matmul reads them transposed as they are (a [D, Nk] copy of every head's keys cost
    XLA:CPU a transpose per attention: ~1.6% of `regime`'s forward at 64 frames)."""
    return jnp.einsum("...qd,...kd->...qk", q, k, preferred_element_type=jnp.float32)


def softmax_attend(q: jax.Array, k: jax.Array, v: jax.Array, bias: jax.Array | None
                    ) -> tuple[jax.Array, jax.Array]:
    """q [..., n, D] (pre-scaled), k [..., Nk, D], v [..., Nk, Dv], bias [..., 1, Nk] or
    None -> ([..., n, Dv], the log-sum-exp of the logits [..., n]) in float32.
    Normalises after the value product: n*Dv divisions instead of n*Nk."""
    logits = logits_of(q, k)
    if bias is not None:
        logits = logits + bias
    m = jax.lax.stop_gradient(logits.max(axis=-1, keepdims=True))
    e = jnp.exp(logits - m)
    out = jnp.matmul(e.astype(v.dtype), v, preferred_element_type=jnp.float32)
    total = e.sum(axis=-1, keepdims=True)
    return out / total, (m + jnp.log(total))[..., 0]


def _forward(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
             block_bytes: int, out_dtype: Any = None, bits: bool = True) -> tuple[jax.Array, jax.Array]:
    """The cache-blocked kernel. q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv], key_bias
    [B, Nk] float32 or None -> ([B, Nq, H, Dv] (float32 when in one block, else
    `out_dtype`, default q's), log-sum-exp of the logits [B, Nq, H] float32).
    bits: hold 16-bit operands as `HalfBuffer` in the loop (XLA:CPU's workaround; the attention
    op passes False for the programs it compiles for other platforms)."""
    b, nq, h, d = q.shape
    nk, dv = k.shape[1], v.shape[-1]
    # (the scale stays a constant: XLA:CPU writes its broadcast out once for the frame
    # blocks a plan runs outside a loop, 3.2 MB at 64 frames of the speed layout, but made
    # from q it changes the logits' last bits, and a near-tie merge decision of `fastvggt`
    # at 16 frames went the other way than FastVGGT's code: docs/history/cpu_speed.md)
    qt = (q * jnp.asarray(scale, q.dtype)).transpose(0, 2, 1, 3)  # [B, H, Nq, D]
    kh = k.transpose(0, 2, 1, 3)  # [B, H, Nk, D]
    vt = v.transpose(0, 2, 1, 3)  # [B, H, Nk, Dv]
    bias = None if key_bias is None else key_bias[:, None, None, :]  # [B, 1, 1, Nk]
    if b * h * nq * nk * 4 <= block_bytes:
        out, lse = softmax_attend(qt, kh, vt, bias)
        return out.transpose(0, 2, 1, 3), lse.transpose(0, 2, 1)

    n, rows = query_blocks(nq, nk, 4, block_bytes)
    qb = jnp.pad(qt, ((0, 0), (0, 0), (0, n * rows - nq), (0, 0))).reshape(b * h * n, rows, d)
    kh, vt = kh.reshape(b * h, nk, d), vt.reshape(b * h, nk, dv)
    # 16-bit operands as bits from the start (a bit view made in the loop is hoisted out
    # of it as a copy of the operand)
    qb, kh, vt = (HalfBuffer.of(t) if bits and is_16bit_float(t) else t for t in (qb, kh, vt))

    def index(t, i):
        return read_buffer(t, lambda a, j: jax.lax.dynamic_index_in_dim(a, j, 0, keepdims=False), i)

    def body(i, acc):
        out, lse = acc
        pair = i // n  # (batch, head) pair of this block
        kb, vb = index(kh, pair), index(vt, pair)
        bb = None if bias is None else dynamic_index(bias[:, 0], pair // h)
        res, res_lse = softmax_attend(index(qb, i), kb, vb, bb)
        return (jax.lax.dynamic_update_index_in_dim(out, res.astype(out.dtype), i, 0),
                jax.lax.dynamic_update_index_in_dim(lse, res_lse, i, 0))

    # (the output buffer made from q: a constant one would live from the program start)
    out_dtype = q.dtype if out_dtype is None else out_dtype
    init = zeros_after((b * h * n, rows, dv), out_dtype, q)
    out, lse = jax.lax.fori_loop(0, b * h * n, body, (init, zeros_after((b * h * n, rows), jnp.float32, init)))
    return (out.reshape(b, h, n * rows, dv)[:, :, :nq].transpose(0, 2, 1, 3),
            lse.reshape(b, h, n * rows)[:, :, :nq].transpose(0, 2, 1))


def blocked_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                      block_bytes: int, out_dtype: Any = None, *, bits: bool = True) -> tuple[jax.Array, jax.Array]:
    """The cache-blocked kernel, with its O(N d) backward. q [B, Nq, H, D], k [B, Nk, H, D],
    v [B, Nk, H, Dv], key_bias [B, Nk] float32 or None -> ([B, Nq, H, Dv] (float32 when
    in one block, else `out_dtype`, default q's), log-sum-exp of the logits [B, Nq, H]
    float32). bits: hold 16-bit operands as `HalfBuffer` in the loop (XLA:CPU's workaround;
    the attention op passes False for the programs it compiles for other platforms).
    Gradients: to q, k, v and key_bias (in their dtypes), from both outputs."""
    out_dtype = None if out_dtype is None else jnp.dtype(out_dtype)
    # the matmul precision in force here: the backward, traced wherever the gradient is
    # taken, runs at the forward's (ops/precision.py)
    precision = jax.config.jax_default_matmul_precision
    return _attention(q, k, v, key_bias, float(scale), int(block_bytes), out_dtype, bool(bits), precision)


def _forward_at(q, k, v, key_bias, scale, block_bytes, out_dtype, bits, precision):
    return _forward(q, k, v, key_bias, scale, block_bytes, out_dtype, bits)


_attention = jax.custom_vjp(_forward_at, nondiff_argnums=(4, 5, 6, 7, 8))


def _attention_fwd(q, k, v, key_bias, scale, block_bytes, out_dtype, bits, precision):
    out, lse = _forward(q, k, v, key_bias, scale, block_bytes, out_dtype, bits)
    return (out, lse), (q, k, v, key_bias, out, lse)


def block_grads(qs: jax.Array, k: jax.Array, v: jax.Array, bias: jax.Array | None, o: jax.Array, do: jax.Array,
                lse: jax.Array, dlse: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The backward of `softmax_attend` for one block of queries (any leading dims):
    qs [..., n, D] (pre-scaled, as the forward took it), k [..., Nk, D], v [..., Nk, Dv],
    bias [..., 1, Nk] float32 or None, o / do the output and its cotangent [..., n, Dv],
    lse / dlse the log-sum-exp and its cotangent [..., n] float32 ->
    (d qs [..., n, D], dk [..., Nk, D], dv [..., Nk, Dv], dS [..., n, Nk]), float32.

        P = exp(s - lse)                      (the forward's weights, recomputed)
        dS = P * (dO v^T - rowsum(dO * O) + dlse)

    the last term being the log-sum-exp's own cotangent (d lse_i / d s_ij = P_ij). The
    weights and dS enter the matmuls in the operands' dtype (as the forward's weights
    enter its value product), every product accumulates in float32."""
    f32 = jnp.float32
    logits = logits_of(qs, k)  # as the forward's, rounding included
    if bias is not None:
        logits = logits + bias
    p = jnp.exp(logits - lse[..., None])
    do_v = do.astype(v.dtype)
    dp = jnp.einsum("...qe,...ke->...qk", do_v, v, preferred_element_type=f32)
    delta = jnp.sum(do.astype(f32) * o.astype(f32), axis=-1) - dlse
    ds = p * (dp - delta[..., None])
    dv = jnp.einsum("...qk,...qe->...ke", p.astype(v.dtype), do_v, preferred_element_type=f32)
    dsk = ds.astype(k.dtype)
    dqs = jnp.einsum("...qk,...kd->...qd", dsk, k, preferred_element_type=f32)
    dk = jnp.einsum("...qk,...qd->...kd", dsk, qs, preferred_element_type=f32)
    return dqs, dk, dv, ds


def _attention_bwd(scale, block_bytes, out_dtype, bits, precision, res, cts):
    """`_grads` at the forward's matmul precision."""
    with precision_scope(precision):
        return _grads(scale, block_bytes, out_dtype, bits, res, cts)


def _grads(scale, block_bytes, out_dtype, bits, res, cts):
    """dq, dk, dv, d key_bias from the cotangents (d out, d lse): the forward's query
    blocks again, one (batch, head) pair at a time; dk, dv and the bias gradient of a pair
    accumulate in float32 over its query blocks (O(N d), never a [Nq, Nk] matrix beyond
    one block's)."""
    q, k, v, key_bias, out, lse = res
    dout, dlse = cts
    f32 = jnp.float32
    b, nq, h, d = q.shape
    nk, dv_ = k.shape[1], v.shape[-1]
    qt = (q * jnp.asarray(scale, q.dtype)).transpose(0, 2, 1, 3)  # [B, H, Nq, D], as the forward's
    kh = k.transpose(0, 2, 1, 3)  # [B, H, Nk, D]
    vt = v.transpose(0, 2, 1, 3)  # [B, H, Nk, Dv]
    ot, dot = out.transpose(0, 2, 1, 3), dout.transpose(0, 2, 1, 3)  # [B, H, Nq, Dv]
    lt, dlt = lse.transpose(0, 2, 1).astype(f32), dlse.transpose(0, 2, 1).astype(f32)  # [B, H, Nq]
    bias = None if key_bias is None else key_bias[:, None, None, :]  # [B, 1, 1, Nk]

    def finish(dqs, dk, dv, dbias):  # [B, H, ...] float32 -> the operands' layouts and dtypes
        dq = (dqs * jnp.asarray(scale, f32)).astype(q.dtype).transpose(0, 2, 1, 3)
        return dq, dk.astype(k.dtype).transpose(0, 2, 1, 3), dv.astype(v.dtype).transpose(0, 2, 1, 3), dbias

    if b * h * nq * nk * 4 <= block_bytes:  # the forward's single block
        dqs, dk, dv, ds = block_grads(qt, kh, vt, bias, ot, dot, lt, dlt)
        return finish(dqs, dk, dv, None if bias is None else ds.sum(axis=(1, 2)))

    n, rows = query_blocks(nq, nk, 4, block_bytes)

    def blocks(t, fill=0.0):  # [B, H, Nq, ...] -> [B * H * n, rows, ...] (padded rows: fill)
        widths = ((0, 0), (0, 0), (0, n * rows - nq)) + ((0, 0),) * (t.ndim - 3)
        return jnp.pad(t, widths, constant_values=fill).reshape((b * h * n, rows) + t.shape[3:])

    # padded rows: zero cotangents and an infinite log-sum-exp (weights exactly 0), so
    # they add nothing to dk, dv or the bias gradient
    qb, ob, dob = blocks(qt), blocks(ot), blocks(dot)
    lb, dlb = blocks(lt, jnp.inf), blocks(dlt)
    kp, vp = kh.reshape(b * h, nk, d), vt.reshape(b * h, nk, dv_)
    qb, kp, vp, ob, dob = (HalfBuffer.of(t) if bits and is_16bit_float(t) else t for t in (qb, kp, vp, ob, dob))

    def index(t, i):
        return read_buffer(t, lambda a, j: jax.lax.dynamic_index_in_dim(a, j, 0, keepdims=False), i)

    def pair_body(pair, acc):
        dq_all, dk_all, dv_all, dbias_all = acc
        kb, vb = index(kp, pair), index(vp, pair)
        bb = None if bias is None else dynamic_index(bias[:, 0], pair // h)

        def block_body(j, inner):
            dq_all, dk, dv, dbias = inner
            i = pair * n + j
            dqs, dki, dvi, ds = block_grads(index(qb, i), kb, vb, bb, index(ob, i), index(dob, i),
                                            index(lb, i), index(dlb, i))
            dq = (dqs * jnp.asarray(scale, f32)).astype(q.dtype)
            dbias = None if dbias is None else dbias + ds.sum(axis=0)
            return jax.lax.dynamic_update_index_in_dim(dq_all, dq, i, 0), dk + dki, dv + dvi, dbias

        zk = zeros_after((nk, d), f32, kb)
        inner = (dq_all, zk, zeros_after((nk, dv_), f32, zk), None if bias is None else zeros_after((nk,), f32, zk))
        dq_all, dk, dv, dbias = jax.lax.fori_loop(0, n, block_body, inner)
        dk_all = jax.lax.dynamic_update_index_in_dim(dk_all, dk.astype(k.dtype), pair, 0)
        dv_all = jax.lax.dynamic_update_index_in_dim(dv_all, dv.astype(v.dtype), pair, 0)
        if dbias is not None:  # heads of one batch element share its bias: add theirs up
            row = pair // h
            dbias_all = jax.lax.dynamic_update_index_in_dim(
                dbias_all, dynamic_index(dbias_all, row) + dbias, row, 0)
        return dq_all, dk_all, dv_all, dbias_all

    # (buffers made from the cotangent: constant ones would live from the program start)
    init = (zeros_after((b * h * n, rows, d), q.dtype, dout), zeros_after((b * h, nk, d), k.dtype, dout),
            zeros_after((b * h, nk, dv_), v.dtype, dout), None if bias is None else zeros_after((b, nk), f32, dout))
    dq, dk, dv, dbias = jax.lax.fori_loop(0, b * h, pair_body, init)
    dq = dq.reshape(b, h, n * rows, d)[:, :, :nq].transpose(0, 2, 1, 3)
    return (dq, dk.reshape(b, h, nk, d).transpose(0, 2, 1, 3), dv.reshape(b, h, nk, dv_).transpose(0, 2, 1, 3),
            dbias)


_attention.defvjp(_attention_fwd, _attention_bwd)
