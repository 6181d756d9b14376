"""Transformer building blocks as pure functions over parameter dicts.

Parameter leaves follow the converter's conventions (see `rvggt_jax/weights/rules.py`):
Linear -> {"kernel": [in, out], "bias": [out]}; LayerNorm -> {"scale", "bias"};
the upstream fused `qkv` Linear is split into {"q", "k", "v"} Linears;
LayerScale -> {"gamma": [C]}.

Attention tensors are token-major, `[B, N, H, D]` (the layout of
`jax.nn.dot_product_attention`), never upstream's `[B, H, N, D]`.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.attention import attention
from rvggt_jax.ops import chunks
from rvggt_jax.ops.chunks import map_tokens, update_tokens
from rvggt_jax.ops.ordering import with_dependency, zeros_from
from rvggt_jax.model.params import Params

# Upstream's aggregator, camera head and DPT use torch's LayerNorm default; DINOv2 uses 1e-6.
TORCH_LN_EPS = 1e-5


def linear(p: Params, x: jax.Array) -> jax.Array:
    """`x @ kernel + bias`; `x` [..., in] -> [..., out] in x's dtype.

    The product runs in x's dtype (the compute dtype: the kernel is cast to it when it is
    stored otherwise) and accumulates in float32, as torch's autocast matmuls do."""
    w = p["kernel"]
    if w.dtype != x.dtype:
        w = w.astype(x.dtype)
    y = jnp.matmul(x, w, preferred_element_type=jnp.float32)
    if "bias" in p:
        y = y + p["bias"].astype(jnp.float32)
    return y.astype(x.dtype)


def layer_norm(p: Params | None, x: jax.Array, eps: float = TORCH_LN_EPS, dtype: Any = None) -> jax.Array:
    """LayerNorm over the last axis; `p=None` is the affine-free variant.

    Statistics and the affine map in float32 whatever x's dtype (bfloat16 statistics lose
    the mean of wide rows); the result in `dtype` (default: x's dtype)."""
    out_dtype = x.dtype if dtype is None else dtype
    shape = x.shape
    # the rows as a [rows, C] matrix (a free reshape, the same values bit for bit): XLA:CPU
    # fuses the row reductions of the qk-norms' [B, N, H, D] worse than those of a matrix
    # (`regime`'s forward at 64 frames of the speed layout -3%, docs/benchmarks.md)
    x = x.astype(jnp.float32).reshape(-1, shape[-1])
    mean = jnp.mean(x, axis=-1, keepdims=True)
    xc = x - mean
    var = jnp.mean(xc * xc, axis=-1, keepdims=True)
    y = xc * jax.lax.rsqrt(var + eps)
    if p is not None:
        y = y * p["scale"].astype(jnp.float32) + p["bias"].astype(jnp.float32)
    return y.astype(out_dtype).reshape(shape)


def gelu(x: jax.Array) -> jax.Array:
    """Exact (erf) GELU, as torch's nn.GELU default: x/2 (1 + erf(x/sqrt(2))), torch's own
    formula, evaluated in float32 (the result in x's dtype). (The tanh form differs by
    ~1e-3; jax.nn.gelu's exact form goes through erfc and runs ~2x slower on CPU.)

    The constants are rows made from x (`zeros_from`), not scalars: XLA merges equal
    broadcasts of a scalar, so blocks outside a loop whose MLPs have one shape (the DINO
    block and the VGGT frame block a compression plan runs once: both [S, P, 4C]) shared
    them, and XLA:CPU wrote each shared one out in full for their YNNPACK fusions (3 x
    12.9 MB at 64 frames in the speed layout, ~7 ms of `regime`). Same values, bit for bit."""
    x32 = x.astype(jnp.float32)
    z = zeros_from(x.shape[-1:], jnp.float32, x32)
    half, one, inv_sqrt2 = z + 0.5, z + 1.0, z + np.float32(1.0 / math.sqrt(2.0))
    return (half * x32 * (one + jax.lax.erf(x32 * inv_sqrt2))).astype(x.dtype)


def mlp(p: Params, x: jax.Array) -> jax.Array:
    """fc1 -> GELU -> fc2, in x's dtype."""
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
    ~15% of a global block on CPU). The whole sequence's tables (`of_sequence`) are
    `chunks.Periodic` (one frame's rows): the chunk loops slice them, a loop run in one
    chunk tiles them in its body; `first` and `frame_rows` read them either way."""

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

    @classmethod
    def of_sequence(cls, frame: "RopeTables", frames: int) -> "RopeTables":
        """The tables of `frames` frames in a row from one frame's [1, P, 1, D], as
        `chunks.Periodic` arrays (one frame's rows), never tiled outside the blocks: a loop
        over token chunks slices each chunk's rows from the period, and a loop run in one
        chunk tiles them in its body, where XLA fuses the tiling into the RoPE product.
        (Tiled once per forward, every global block read the [1, frames * P, 1, D] tables
        from memory: at 64 frames of 168 x 224 in the speed layout, `regime`'s forward
        took 1.7% longer, docs/benchmarks.md; at 1000 frames of VGGT-1B the tiled tables
        were 2 x 266 MB.)"""
        n = frame.cos.shape[1] * frames
        return cls(chunks.Periodic(frame.cos, n), chunks.Periodic(frame.sin, n))

    def _leading(self, fn) -> "RopeTables":
        """fn applied to both tables' leading rows: one period of a periodic table, all of
        a plain one."""
        return RopeTables(*(fn(t.period if isinstance(t, chunks.Periodic) else t) for t in (self.cos, self.sin)))

    def first(self, rows: int) -> "RopeTables":
        """The tables of the first `rows` tokens (`rows` within one period when periodic)."""
        def head(t):
            if rows > t.shape[1]:
                raise ValueError(f"{rows} rows asked of RoPE tables holding {t.shape[1]}")
            return t[:, :rows]
        return self._leading(head)

    def frame_rows(self, local: jax.Array) -> "RopeTables":
        """Rows `local` (indices within a frame, any shape) of every table, [*local.shape, 1, D]."""
        return self._leading(lambda t: jnp.take(t[0], local, axis=0, mode="clip"))

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
    # (the tables made from x, the same values: constants broadcast to one shape are merged
    # across the blocks outside a loop, and XLA:CPU writes the merged broadcast out)
    tables = RopeTables(with_dependency(tables.cos, x), with_dependency(tables.sin, x))
    q = x.shape[-1] // 4
    # rotate-half within each half: (a, b, c, d) quarters -> (-b, a, -d, c)
    rotated = jnp.concatenate([-x[..., q:2 * q], x[..., :q], -x[..., 3 * q:], x[..., 2 * q:3 * q]], axis=-1)
    return x * tables.cos.astype(x.dtype) + rotated * tables.sin.astype(x.dtype)


# ---------------------------------------------------------------------------------------
# Attention (the op itself lives in rvggt_jax/ops/attention.py)
# ---------------------------------------------------------------------------------------


def attention_qkv(p: Params, x: jax.Array, num_heads: int, pos: "jax.Array | RopeTables | None" = None,
                  rope_freq: float | None = None, parts: str = "qkv") -> tuple[jax.Array, ...]:
    """q, k, v [B, N, H, D] of the upstream Attention (those named in `parts`, in that
    order), in x's dtype: projection, qk-norm (when the params have `q_norm`), then RoPE
    (when `pos` is given: integer positions [B|1, N, 2] with `rope_freq`, or their
    `RopeTables`). qk-norm and RoPE run in float32 (as under torch's autocast, where the
    norm's float32 output feeds RoPE)."""
    b, n, c = x.shape
    f32 = jnp.float32
    out = []
    for name in parts:
        t = linear(p[name], x)
        t = t.reshape(b, n, num_heads, t.shape[-1] // num_heads)  # (a head group's weights: fewer columns)
        if name in "qk":
            if f"{name}_norm" in p:
                t = layer_norm(p[f"{name}_norm"], t, dtype=f32)
            if pos is not None:
                t = rope_2d(t.astype(f32), pos, rope_freq)
            t = t.astype(x.dtype)
        out.append(t)
    return tuple(out)


def block_qkv(p: Params, x: jax.Array, num_heads: int, tables: "RopeTables | None" = None,
               eps: float = TORCH_LN_EPS, dtype: Any = None, parts: str = "qkv") -> tuple[jax.Array, ...]:
    """q, k, v [B, N, H, D] (those in `parts`) in `dtype` of a block's attention from its
    residual stream x [B, N, C]: norm1, projection, qk-norm, RoPE (`tables` [1|B, N, 1, D],
    or None), over token chunks written into the results (the projections' float32
    products and the normalised x never exist for the whole sequence at once)."""
    dtype = x.dtype if dtype is None else dtype
    inputs = (x,) if tables is None else (x, tables.cos, tables.sin)
    return map_tokens(block_qkv_rows(p, num_heads, eps, dtype, parts), inputs,
                      bytes_per_row=x.shape[0] * x.shape[-1] * 4 * len(parts) + x.shape[-1] * 4)


def block_qkv_rows(p: Params, num_heads: int, eps: float, dtype: Any, parts: str = "qkv"):
    """The per-token function of `block_qkv`: (x rows [B, r, C], cos, sin [1|B, r, 1, D]
    or nothing) -> q, k, v rows."""
    def one(xc, *tc):
        pos = RopeTables(*tc) if tc else None
        return attention_qkv(p["attn"], layer_norm(p["norm1"], xc, eps, dtype), num_heads, pos, parts=parts)

    return one


# ---------------------------------------------------------------------------------------
# The transformer block (written once) and its attention hooks
# ---------------------------------------------------------------------------------------


def block_with_attention(p: Params, x: jax.Array, attend, inputs: tuple = (), *, eps: float = TORCH_LN_EPS,
                         dtype: Any = None, projected: bool = False, with_aux: bool = False, axis: int = 1,
                         bytes_per_row: int | None = None, multiple: int = 8):
    """The pre-norm transformer block with LayerScale, the one copy every block runs (plain,
    DINO, camera trunk, compressed global): each chunk of rows of the residual stream x
    [B, N, C] becomes x + ls1(proj(attention)), then + ls2(mlp(norm2(.))).

    The attention is the hook `attend(x_rows, *input_rows)`, given the chunk's rows of x
    and of `inputs` (each chunked along `axis` like x): it returns the attention output
    of those rows, heads [..., H, D] (then projected here by `attn.proj`) or, with
    `projected`, rows [..., C] it projected itself (a merged attention projects its merged
    rows before unmerging them); with `with_aux`, a pair (output, aux rows), aux stitched
    along `axis` and returned too. Hooks: `self_attention` (each chunk attends within
    itself: whole sequences per chunk), `attention_to` (queries of the chunk against given
    K/V), the unmerge of the merging block (`compression.merged_layer`), the saliency of
    `patch_embed`.

    x is kept in its own dtype (float32 in the model); norms, attention and MLP compute in
    `dtype` (default x's): torch's autocast. One in-place pass over chunks of rows
    (`chunks.update_tokens`; with `with_aux` the results are new arrays, `map_tokens`) of
    `bytes_per_row` (default: one token's float32 MLP hidden layer per sequence)."""
    c = x.shape[-1]
    proj = p["attn"]["proj"]
    if bytes_per_row is None:
        bytes_per_row = x.shape[0] * p["mlp"]["fc1"]["kernel"].shape[-1] * 4

    def rows(xc, *ic):
        out, aux = attend(xc, *ic) if with_aux else (attend(xc, *ic), None)
        if not projected:
            out = linear(proj, out.reshape(xc.shape[:2] + (c,)))
        y = _residual_mlp(p, xc, out, eps, dtype)
        return (y, aux) if with_aux else y

    if with_aux:
        return map_tokens(rows, (x, *inputs), axis=axis, bytes_per_row=bytes_per_row, multiple=multiple)
    return update_tokens(rows, x, inputs, axis=axis, bytes_per_row=bytes_per_row, multiple=multiple)


def self_attention(p: Params, num_heads: int, eps: float = TORCH_LN_EPS, dtype: Any = None):
    """`block_with_attention`'s hook for rows that attend among themselves: (x rows [B, r, C], cos,
    sin [1|B, r, 1, D] or nothing) -> attention output [B, r, H, D]."""
    qkv = block_qkv_rows(p, num_heads, eps, dtype)
    return lambda xc, *tc: attention(*qkv(xc, *tc))


def attention_to(p: Params, num_heads: int, k: jax.Array, v: jax.Array, key_bias: jax.Array | None = None,
                 eps: float = TORCH_LN_EPS, dtype: Any = None):
    """`block_with_attention`'s hook for the query side of a long sequence: each chunk's Q (norm1,
    projection, qk-norm, RoPE with its rows of cos, sin) attends to the given K/V
    [B, Nk, H, D] (with `key_bias` [B, Nk])."""
    q_of = block_qkv_rows(p, num_heads, eps, dtype, "q")
    return lambda xc, *tc: attention(q_of(xc, *tc)[0], k, v, key_bias)


def block(p: Params, x: jax.Array, num_heads: int, pos: "jax.Array | RopeTables | None" = None,
          rope_freq: float | None = None, eps: float = TORCH_LN_EPS, dtype: Any = None) -> jax.Array:
    """Pre-norm transformer block with LayerScale over B sequences: x [B, N, C] ->
    [B, N, C], attention within each sequence (`block_with_attention`).

    x is the residual stream (kept in its own dtype, float32 in the model); attention and
    MLP compute in `dtype` (default x's): the mixed precision of torch's autocast.
    pos: RoPE tables [1|B, N, 1, D] or integer positions [1|B, N, 2] (with `rope_freq`),
    or None.

    The block is one in-place pass over x. Short sequences (frames, DINO images): whole
    sequences per chunk, each chunk a complete block. Long sequences (the global blocks):
    K and V of the whole sequence first, then chunks of queries, each attending to all
    keys and finishing its rows (projection, residual, MLP). Only K and V ever exist for
    the whole sequence."""
    b, n, c = x.shape
    dtype = x.dtype if dtype is None else dtype
    if pos is not None and not isinstance(pos, RopeTables):
        pos = RopeTables.from_positions(pos, c // num_heads, rope_freq)
    hidden = p["mlp"]["fc1"]["kernel"].shape[-1]
    tables = () if pos is None else (pos.cos, pos.sin)
    per_sequence = n * hidden * 4
    if per_sequence <= chunks.TOKEN_CHUNK_BYTES:
        whole = dict(eps=eps, dtype=dtype, axis=0, bytes_per_row=per_sequence, multiple=1)
        attend = self_attention(p, num_heads, eps, dtype)
        tables = tuple(map(chunks.whole, tables))
        if tables and tables[0].shape[0] != 1:  # per-sequence positions: chunk them too
            return block_with_attention(p, x, attend, tables, **whole)
        return block_with_attention(p, x, lambda xc: attend(xc, *tables), **whole)

    x, (k, v) = chunks.map_tokens_through(block_qkv_rows(p, num_heads, eps, dtype, "kv"), x, tables,
                                          bytes_per_row=b * c * 4 * 2 + c * 4)
    return block_with_attention(p, x, attention_to(p, num_heads, k, v, None, eps, dtype), tables, eps=eps, dtype=dtype)


def _residual_mlp(p: Params, x: jax.Array, attn_rows: jax.Array, eps: float = TORCH_LN_EPS, dtype: Any = None
                 ) -> jax.Array:
    """x + ls1(attn_rows), then + ls2(mlp(norm2(.))): rows of the residual stream x
    [..., C] and the attention branch's (projected) output [..., C]."""
    dtype = x.dtype if dtype is None else dtype
    x = x + layer_scale(p.get("ls1"), attn_rows).astype(x.dtype)
    return x + layer_scale(p.get("ls2"), mlp(p["mlp"], layer_norm(p["norm2"], x, eps, dtype))).astype(x.dtype)


def select_block(blocks: Params, indices, i: jax.Array) -> Params:
    """The params of block `indices[i]` of numbered blocks ({"0": ..., "1": ...}), for a
    `lax.scan` over `i`: one compiled body instead of one per block. The one way the
    model scans numbered blocks (aggregator, DINO, camera trunk, tracker). Picked by
    `lax.switch` rather than stacking all blocks along a new axis, because a stack copies
    every weight on every call."""
    indices = list(indices)
    if len(indices) == 1:
        return blocks[str(indices[0])]
    return jax.lax.switch(i, [lambda j=j: blocks[str(j)] for j in indices])


def block_stack(blocks: Params, indices, x: jax.Array, num_heads: int,
                pos: "jax.Array | RopeTables | None" = None, rope_freq: float | None = None,
                eps: float = TORCH_LN_EPS, dtype: Any = None, remat: Any = None) -> jax.Array:
    """Apply numbered blocks `indices` (in order) with `lax.scan`; `remat`: how each block
    runs in a training step, a wrapper such as `jax.checkpoint` (`model.remat.checkpoint`
    under `VGGTConfig.remat`), or None."""
    def step(h, i):
        return block(select_block(blocks, indices, i), h, num_heads, pos, rope_freq, eps, dtype), None

    if remat is not None:
        step = remat(step)

    return jax.lax.scan(step, x, jnp.arange(len(indices)))[0]
