"""The one attention op of the model: every attention (frame, global, compressed with the
size bias, DINO, camera trunk, tracker) calls `attention`.

    out = attention(q, k, v)                       # softmax(q k^T / sqrt(D)) v
    out = attention(q, k, v, key_bias=log_g)       # + an additive bias per key [B, Nk]

It picks its kernel by name (`implementation`), like MaxText's attention op:

  "blocked"  (the default, but for half precision on GPU) one (batch, head) pair and a
             cache-sized block of query rows at a time (`query_blocks`), logits in float32, normalised after the
             value product. The key bias is added to each logits block.
  "cudnn"    (the default for bfloat16/float16 on GPU) `jax.nn.dot_product_attention`'s
             cuDNN flash kernel; "xla" is its plain XLA form (forms all logits: for
             checks, not long sequences). A key bias is folded into the operands
             (`fold_key_bias`: Q' = [Q, 1, 0..], K' = [K, bias / scale, 0..], V' = [V, 0..];
             two columns hi + lo in 16-bit dtypes)
             so that flash kernels, which take no per-key bias, still apply it; the head
             dimension is zero-padded to a multiple of 8 (cuDNN's rule; D = 64 + the bias
             column would be 65).

Working memory does not grow with the number of keys beyond K and V themselves (and
their head-major copies): the blocked path holds one [rows, Nk] logits block per step
with rows chosen so that the block fits LOGITS_BLOCK_BYTES; the fused GPU kernels never
form the logits.

Precision: q, k, v in the compute dtype (float32 or bfloat16); logits, softmax
statistics and the value accumulation in float32; the result in q's dtype.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.chunks import Bits16, dynamic_index, is_16bit_float, read_buffer, zeros_after

if TYPE_CHECKING:
    from rvggt_jax.ops.shards import FrameShards

IMPLEMENTATIONS = ("blocked", "xla", "cudnn")

# Bytes of one logits block of the blocked kernel. Global attention over thousands of
# tokens cannot hold all [B, H, Nq, Nk] logits in cache; one (batch, head) pair and a
# slice of query rows at a time keeps the block in L2/L3 and gives the value matmul
# hundreds of rows (XLA:CPU splits a matmul across threads by rows: under ~512 rows it
# runs on one core). 24 MiB measured best on a 2-core EPYC (32 MiB L3).
LOGITS_BLOCK_BYTES = 24 * 2**20

# A key bias this negative removes the key: exp(NEG_BIAS - max) is exactly 0 in float32,
# and, being finite, a row whose keys are all removed can never turn into NaN.
NEG_BIAS = -1.0e4

# cuDNN's fused attention needs a head dimension that is a multiple of 8, at most 128.
CUDNN_HEAD_MULTIPLE = 8
CUDNN_MAX_HEAD_DIM = 128


def default_implementation(dtype: Any = jnp.float32) -> str:
    """"cudnn" for bfloat16/float16 operands on a GPU, else "blocked" (cuDNN's fused
    kernel takes no float32; the blocked kernel keeps float32 memory bounded anywhere)."""
    half = jnp.dtype(dtype) in (jnp.dtype(jnp.bfloat16), jnp.dtype(jnp.float16))
    return "cudnn" if half and jax.default_backend() == "gpu" else "blocked"


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


def _softmax_attend(q: jax.Array, kt: jax.Array, v: jax.Array, bias: jax.Array | None
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


def _blocked(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
             block_bytes: int, out_dtype: Any = None) -> tuple[jax.Array, jax.Array]:
    """The CPU kernel. q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv], key_bias
    [B, Nk] float32 or None -> ([B, Nq, H, Dv] (float32 when in one block, else
    `out_dtype`, default q's), log-sum-exp of the logits [B, Nq, H] float32)."""
    b, nq, h, d = q.shape
    nk, dv = k.shape[1], v.shape[-1]
    qt = (q * jnp.asarray(scale, q.dtype)).transpose(0, 2, 1, 3)  # [B, H, Nq, D]
    kt = k.transpose(0, 2, 3, 1)  # [B, H, D, Nk]
    vt = v.transpose(0, 2, 1, 3)  # [B, H, Nk, Dv]
    bias = None if key_bias is None else key_bias[:, None, None, :]  # [B, 1, 1, Nk]
    if b * h * nq * nk * 4 <= block_bytes:
        out, lse = _softmax_attend(qt, kt, vt, bias)
        return out.transpose(0, 2, 1, 3), lse.transpose(0, 2, 1)

    n, rows = query_blocks(nq, nk, 4, block_bytes)
    qb = jnp.pad(qt, ((0, 0), (0, 0), (0, n * rows - nq), (0, 0))).reshape(b * h * n, rows, d)
    kt, vt = kt.reshape(b * h, d, nk), vt.reshape(b * h, nk, dv)
    # 16-bit operands as bits from the start: a 16-bit slice in the loop is made from a
    # bit view that XLA would copy whole out of the loop, next to the operand itself
    qb, kt, vt = (Bits16.of(t) if is_16bit_float(t) else t for t in (qb, kt, vt))

    def index(t, i):
        return read_buffer(t, lambda a, j: jax.lax.dynamic_index_in_dim(a, j, 0, keepdims=False), i)

    def body(i, acc):
        out, lse = acc
        pair = i // n  # (batch, head) pair of this block
        kb, vb = index(kt, pair), index(vt, pair)
        bb = None if bias is None else dynamic_index(bias[:, 0], pair // h)
        res, res_lse = _softmax_attend(index(qb, i), kb, vb, bb)
        return (jax.lax.dynamic_update_index_in_dim(out, res.astype(out.dtype), i, 0),
                jax.lax.dynamic_update_index_in_dim(lse, res_lse, i, 0))

    # the output buffer is made from q, not a constant: XLA would hoist a constant one to
    # the program start and share it between calls (see chunks.zeros_after)
    out_dtype = q.dtype if out_dtype is None else out_dtype
    init = zeros_after((b * h * n, rows, dv), out_dtype, q)
    out, lse = jax.lax.fori_loop(0, b * h * n, body, (init, zeros_after((b * h * n, rows), jnp.float32, init)))
    return (out.reshape(b, h, n * rows, dv)[:, :, :nq].transpose(0, 2, 1, 3),
            lse.reshape(b, h, n * rows)[:, :, :nq].transpose(0, 2, 1))


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
        block_bytes = LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes
        return _blocked(q, k, v, bias32, scale, block_bytes)[0].astype(q.dtype)

    dv = v.shape[-1]
    multiple = CUDNN_HEAD_MULTIPLE if implementation == "cudnn" else 1
    qf, kf, vf = fold_key_bias(q, k, v, bias32, scale, multiple)
    if implementation == "cudnn" and qf.shape[-1] > CUDNN_MAX_HEAD_DIM:
        raise ValueError(f"cuDNN attention takes head dims up to {CUDNN_MAX_HEAD_DIM}; got {qf.shape[-1]}")
    out = jax.nn.dot_product_attention(qf, kf, vf, scale=scale, implementation=implementation)
    return out[..., :dv].astype(q.dtype)


def log_sizes(sizes: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """The size bias log g [B, Nk] (float32): log of the group sizes, NEG_BIAS for empty
    slots (g = 0)."""
    lg = jnp.log(jnp.maximum(sizes.astype(jnp.float32), 1.0))
    if valid is not None:
        lg = jnp.where(valid, lg, np.float32(NEG_BIAS))
    return lg


def ring_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, shards: "FrameShards",
                   extra: tuple = (), *, scale: float | None = None,
                   block_bytes: int | None = None) -> jax.Array:
    """`attention` of this device's queries to keys split over devices, without ever
    holding more than two devices' keys: q [B, Nq, H, D]; k, v [B, Nk, H, D] and
    key_bias [B, Nk] (or None) this device's share of the keys; `extra`: (k, v, bias)
    triples every device attends to as they are (replicated keys). Returns
    [B, Nq, H, Dv] in q's dtype.

    The shares travel around the devices (`FrameShards.ring_shift`, a collective permute
    per step); each step's partial attention, with its log-sum-exp, is folded into a
    running float32 result (the online softmax of flash attention, across devices). On
    one device: the own keys, then the extra ones, folded the same way."""
    d = q.shape[-1]
    scale = 1.0 / math.sqrt(d) if scale is None else float(scale)
    block_bytes = LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes

    def part(kk, vv, bb):
        return _blocked(q, kk, vv, None if bb is None else bb.astype(jnp.float32), scale, block_bytes, jnp.float32)

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
