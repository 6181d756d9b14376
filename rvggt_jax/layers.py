"""Transformer building blocks as pure functions over parameter dicts.

Parameter leaves follow the converter's conventions (see `convert/rules.py`):
Linear -> {"kernel": [in, out], "bias": [out]}; LayerNorm -> {"scale", "bias"};
the upstream fused `qkv` Linear is split into {"q", "k", "v"} Linears;
LayerScale -> {"gamma": [C]}.

Attention tensors are token-major, `[B, N, H, D]` (the layout of
`jax.nn.dot_product_attention`), never upstream's `[B, H, N, D]`.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

Params = Mapping[str, Any]

# Upstream's aggregator, camera head and DPT use torch's LayerNorm default; DINOv2 uses 1e-6.
TORCH_LN_EPS = 1e-5


def linear(p: Params, x: jax.Array) -> jax.Array:
    """`x @ kernel + bias`; `x` [..., in] -> [..., out]."""
    y = jnp.matmul(x, p["kernel"])
    if "bias" in p:
        y = y + p["bias"]
    return y


def layer_norm(p: Params | None, x: jax.Array, eps: float = TORCH_LN_EPS) -> jax.Array:
    """LayerNorm over the last axis; `p=None` is the affine-free variant."""
    mean = jnp.mean(x, axis=-1, keepdims=True)
    xc = x - mean
    var = jnp.mean(xc * xc, axis=-1, keepdims=True)
    y = xc * jax.lax.rsqrt(var + eps)
    if p is not None:
        y = y * p["scale"] + p["bias"]
    return y


def gelu(x: jax.Array) -> jax.Array:
    """Exact (erf) GELU, as torch's nn.GELU default: x/2 (1 + erf(x/sqrt(2))), torch's own
    formula. (The tanh form differs by ~1e-3; jax.nn.gelu's exact form goes through erfc
    and runs ~2x slower on CPU.)"""
    return 0.5 * x * (1.0 + jax.lax.erf(x * np.float32(1.0 / math.sqrt(2.0))).astype(x.dtype))


def mlp(p: Params, x: jax.Array) -> jax.Array:
    """fc1 -> GELU -> fc2."""
    return linear(p["fc2"], gelu(linear(p["fc1"], x)))


def layer_scale(p: Params | None, x: jax.Array) -> jax.Array:
    return x if p is None else x * p["gamma"]


# ---------------------------------------------------------------------------------------
# 2D rotary position embedding
# ---------------------------------------------------------------------------------------


def patch_positions(h: int, w: int, num_special: int) -> np.ndarray:
    """Integer (y, x) RoPE positions of one frame: `[num_special + h*w, 2]`.

    Special tokens (camera, registers) sit at (0, 0); patch (i, j) at (i + 1, j + 1),
    row-major, as upstream's PositionGetter + 1."""
    yy, xx = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    grid = np.stack([yy.ravel(), xx.ravel()], axis=-1) + 1
    return np.concatenate([np.zeros((num_special, 2), np.int32), grid.astype(np.int32)], axis=0)


@jax.tree_util.register_pytree_node_class
class RopeTables:
    """cos and sin of the 2D RoPE angles, each [B|1, N, 1, D] (broadcast over heads).

    A forward pass has two position sets (one frame, all frames) shared by its 48 blocks:
    building the tables once and passing them as `pos` keeps the trigonometry out of the
    blocks (XLA fuses cos/sin into every consumer, recomputing them per head and block:
    ~15% of a global block on CPU). Indexing slices both tables alike
    (`tables[:, :L]` = the first L tokens)."""

    def __init__(self, cos: jax.Array, sin: jax.Array):
        self.cos, self.sin = cos, sin

    @classmethod
    def from_positions(cls, pos: jax.Array, head_dim: int, freq: float) -> "RopeTables":
        """pos [B|1, N, 2] integer (y, x): the first half of the head dimension rotates
        with y, the second with x; each half in the rotate-half convention."""
        d = head_dim // 2
        inv_freq = jnp.asarray(1.0 / (freq ** (np.arange(0, d, 2, dtype=np.float32) / d)), jnp.float32)
        angles = [pos[..., axis].astype(jnp.float32)[..., None] * inv_freq for axis in (0, 1)]  # [B, N, d/2]
        angles = jnp.concatenate([angles[0], angles[0], angles[1], angles[1]], axis=-1)[:, :, None, :]
        return cls(jnp.cos(angles), jnp.sin(angles))

    def __getitem__(self, idx) -> "RopeTables":
        return RopeTables(self.cos[idx], self.sin[idx])

    def tree_flatten(self):
        return (self.cos, self.sin), None

    @classmethod
    def tree_unflatten(cls, _, children):
        return cls(*children)


def rope_2d(x: jax.Array, pos: "jax.Array | RopeTables", freq: float | None = None) -> jax.Array:
    """2D RoPE: the first half of the head dimension rotates with y, the second with x.

    x [B, N, H, D]; pos [B|1, N, 2] integer (y, x) positions (with `freq`), or their
    precomputed `RopeTables`."""
    tables = pos if isinstance(pos, RopeTables) else RopeTables.from_positions(pos, x.shape[-1], freq)
    q = x.shape[-1] // 4
    # rotate-half within each half: (a, b, c, d) quarters -> (-b, a, -d, c)
    rotated = jnp.concatenate([-x[..., q:2 * q], x[..., :q], -x[..., 3 * q:], x[..., 2 * q:3 * q]], axis=-1)
    return x * tables.cos.astype(x.dtype) + rotated * tables.sin.astype(x.dtype)


# ---------------------------------------------------------------------------------------
# Attention
# ---------------------------------------------------------------------------------------


# Bytes of one logits block when attention is computed block by block. Global attention
# over thousands of tokens cannot hold all [B, H, Nq, Nk] logits in cache; one (batch,
# head) pair and a slice of query rows at a time keeps the block in L2/L3 and gives the
# value matmul hundreds of rows (XLA:CPU splits a matmul across threads by rows: under
# ~512 rows it runs on one core). 24 MiB measured best on a 2-core EPYC (32 MiB L3):
# 3152 tokens x 4 heads runs ~15% faster than 4 heads x 256 rows, and 2x faster than
# 2 heads per block.
LOGITS_BLOCK_BYTES = 24 * 2**20


def _softmax_attend(q: jax.Array, kt: jax.Array, v: jax.Array, bias: jax.Array | None) -> jax.Array:
    """q [..., n, D] (pre-scaled), kt [..., D, Nk], v [..., Nk, Dv] -> [..., n, Dv].
    Normalises after the value product: n*Dv divisions instead of n*Nk."""
    logits = q @ kt
    if bias is not None:
        logits = logits + bias
    e = jnp.exp(logits - jax.lax.stop_gradient(logits.max(axis=-1, keepdims=True)))
    return (e @ v) / e.sum(axis=-1, keepdims=True)


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


def _blocked_attend(qt: jax.Array, kt: jax.Array, vt: jax.Array, bias: jax.Array | None,
                    block_bytes: int) -> jax.Array:
    """`_softmax_attend` one (batch, head) pair and one block of query rows at a time.
    qt [B, H, Nq, D], kt [B, H, D, Nk], vt [B, H, Nk, Dv], bias None or broadcastable to
    [B, H, 1, Nk] -> [B, H, Nq, Dv]."""
    b, h, nq, d = qt.shape
    nk, dv = vt.shape[-2:]
    n, rows = query_blocks(nq, nk, qt.dtype.itemsize, block_bytes)
    qb = jnp.pad(qt, ((0, 0), (0, 0), (0, n * rows - nq), (0, 0))).reshape(b * h * n, rows, d)
    kt, vt = kt.reshape(b * h, d, nk), vt.reshape(b * h, nk, dv)
    if bias is not None:
        bias = jnp.broadcast_to(bias, (b, h, 1, nk)).reshape(b * h, 1, nk)

    def one_block(args):
        q_rows, i = args
        pair = i // n

        def take(x):
            return None if x is None else jax.lax.dynamic_index_in_dim(x, pair, 0, keepdims=False)

        return _softmax_attend(q_rows, take(kt), take(vt), take(bias))

    out = jax.lax.map(one_block, (qb, jnp.arange(b * h * n)))
    return out.reshape(b, h, n * rows, dv)[:, :, :nq]


def attention(q: jax.Array, k: jax.Array, v: jax.Array, bias: jax.Array | None = None,
              scale: float | None = None, block_bytes: int | None = None) -> jax.Array:
    """softmax(q k^T * scale + bias) v over tokens.

    q [B, Nq, H, D], k/v [B, Nk, H, D(v)], bias broadcastable to [B, H, Nq, Nk];
    returns [B, Nq, H, Dv]. `scale` defaults to 1/sqrt(D). When all logits would take
    more than `block_bytes` (default LOGITS_BLOCK_BYTES), they are formed block by block
    (`query_blocks`); a bias with a query axis disables blocking."""
    scale = 1.0 / math.sqrt(q.shape[-1]) if scale is None else scale
    block_bytes = LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes
    b, nq, h, _ = q.shape
    nk = k.shape[1]
    qt = (q * jnp.asarray(scale, q.dtype)).transpose(0, 2, 1, 3)
    kt = k.transpose(0, 2, 3, 1)
    vt = v.transpose(0, 2, 1, 3)
    per_query_bias = bias is not None and bias.ndim >= 2 and bias.shape[-2] != 1
    if per_query_bias or b * h * nq * nk * q.dtype.itemsize <= block_bytes:
        out = _softmax_attend(qt, kt, vt, bias)
    else:
        out = _blocked_attend(qt, kt, vt, bias, block_bytes)
    return out.transpose(0, 2, 1, 3)


def qkv_heads(p: Params, x: jax.Array, num_heads: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Project x [B, N, C] to q, k, v, each [B, N, H, C/H]."""
    b, n, c = x.shape

    def heads(t):
        return t.reshape(b, n, num_heads, c // num_heads)

    return heads(linear(p["q"], x)), heads(linear(p["k"], x)), heads(linear(p["v"], x))


def attention_qkv(p: Params, x: jax.Array, num_heads: int, pos: "jax.Array | RopeTables | None" = None,
                  rope_freq: float | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """q, k, v [B, N, H, D] of the upstream Attention: projection, qk-norm (when the
    params have `q_norm`), then RoPE (when `pos` is given: integer positions [B|1, N, 2]
    with `rope_freq`, or their `RopeTables`)."""
    q, k, v = qkv_heads(p, x, num_heads)
    if "q_norm" in p:
        q = layer_norm(p["q_norm"], q)
        k = layer_norm(p["k_norm"], k)
    if pos is not None:
        q = rope_2d(q, pos, rope_freq)
        k = rope_2d(k, pos, rope_freq)
    return q, k, v


def self_attention(p: Params, x: jax.Array, num_heads: int, pos: "jax.Array | RopeTables | None" = None,
                   rope_freq: float | None = None) -> jax.Array:
    """Upstream `Attention.forward`: x [B, N, C] -> [B, N, C]."""
    b, n, c = x.shape
    q, k, v = attention_qkv(p, x, num_heads, pos, rope_freq)
    out = attention(q, k, v).reshape(b, n, c)
    return linear(p["proj"], out)


def block(p: Params, x: jax.Array, num_heads: int, pos: "jax.Array | RopeTables | None" = None,
          rope_freq: float | None = None, eps: float = TORCH_LN_EPS) -> jax.Array:
    """Pre-norm transformer block with LayerScale: x [B, N, C] -> [B, N, C]."""
    x = x + layer_scale(p.get("ls1"), self_attention(p["attn"], layer_norm(p["norm1"], x, eps),
                                                      num_heads, pos, rope_freq))
    return x + layer_scale(p.get("ls2"), mlp(p["mlp"], layer_norm(p["norm2"], x, eps)))


def select_block(blocks: Params, indices, i: jax.Array) -> Params:
    """The params of block `indices[i]` of numbered blocks ({"0": ..., "1": ...}), for a
    `lax.scan` over `i`: one compiled body instead of one per block. Picked by
    `lax.switch` rather than stacking all blocks along a new axis, because a stack copies
    every weight on every call (~3% of the small benchmark forward; 2.4 GB per call at
    the 1B layout)."""
    return jax.lax.switch(i, [lambda j=j: blocks[str(j)] for j in indices])


def block_stack(blocks: Params, indices, x: jax.Array, num_heads: int,
                pos: "jax.Array | RopeTables | None" = None, rope_freq: float | None = None,
                eps: float = TORCH_LN_EPS) -> jax.Array:
    """Apply numbered blocks `indices` (in order) with `lax.scan`."""
    def step(h, i):
        return block(select_block(blocks, indices, i), h, num_heads, pos, rope_freq, eps), None

    return jax.lax.scan(step, x, jnp.arange(len(indices)))[0]
