"""Transformer building blocks as pure functions over parameter dicts.

Parameter leaves follow the converter's conventions (see `rvggt_jax/model/param_rules.py`):
Linear -> {"kernel": [in, out], "bias": [out]}; LayerNorm -> {"scale", "bias"};
the upstream fused `qkv` Linear is split into {"q", "k", "v"} Linears;
LayerScale -> {"gamma": [C]}.

Attention tensors are token-major, `[B, N, H, D]` (the layout of
`jax.nn.dot_product_attention`), never upstream's `[B, H, N, D]`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.attention import NEG_BIAS, attention
from rvggt_jax.ops.ring import ring_attention
from rvggt_jax.ops.shards import frame_layout
from rvggt_jax.ops import chunks
from rvggt_jax.ops.chunks import map_tokens, update_tokens
from rvggt_jax.ops.ordering import ordered_after
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
    # the rows as a [rows, C] matrix (a free reshape, the same values bit for bit): the
    # qk-norms' row reductions run faster so (docs/history/cpu_speed.md)
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
    ~1e-3; jax.nn.gelu's exact form goes through erfc and runs ~2x slower on CPU.)"""
    x32 = x.astype(jnp.float32)
    return (0.5 * x32 * (1.0 + jax.lax.erf(x32 * np.float32(1.0 / math.sqrt(2.0))))).astype(x.dtype)


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
    blocks (cos/sin fused into every consumer were recomputed per head and block: ~15%
    of a global block on CPU). The whole sequence's tables (`of_sequence`) are
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
        chunk tiles them in its body, fused into the RoPE product.
        (Tiled once per forward, every global block read the [1, frames * P, 1, D] tables
        from memory: at 64 frames of 168 x 224 in the speed layout, `regime`'s forward
        took 1.7% longer, docs/history/cpu_speed.md; at 1000 frames of VGGT-1B the tiled tables
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
    # (the tables made after x, the same values: a constant shared by the blocks outside
    # a loop is otherwise written out whole: docs/memory_layout.md)
    tables = RopeTables(ordered_after(tables.cos, x), ordered_after(tables.sin, x))
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


@dataclasses.dataclass(frozen=True)
class BlockConfig:
    """How a transformer block computes (frozen, hashable): heads, LayerNorm eps, the
    compute dtype of norms, attention and MLP (None: the residual stream's own, float32
    in the model), the RoPE frequency for integer positions, the attention kernel by name
    (`ops.attention.KERNELS`)."""

    num_heads: int
    eps: float = TORCH_LN_EPS
    dtype: Any = None
    rope_freq: float = 100.0
    kernel: str = "auto"

    @classmethod
    def of(cls, config) -> "BlockConfig":
        """The aggregator's blocks under a `VGGTConfig`: its heads, RoPE frequency,
        compute dtype and attention kernel."""
        return cls(config.num_heads, dtype=config.compute_dtype, rope_freq=config.rope_freq, kernel=config.attention)


def block(p: Params, x: jax.Array, attend, cfg: BlockConfig) -> jax.Array:
    """Upstream's `Block` (pre-norm, LayerScale) on rows x [..., C] of the residual stream:

        x = x + ls1(attend(norm1(x)))
        x = x + ls2(mlp(norm2(x)))

    `attend` maps the normalised rows [..., C] (in cfg.dtype) to the attention branch's
    output rows [..., C], projected (`self_attention`, `attention_to`, or a compressed
    layer's unmerge). x keeps its dtype; the branches compute in cfg.dtype, as under
    torch's autocast. Any chunk of rows is a complete block: the callers run it over
    chunks of the sequence (`sequence_block`, `ops/chunks.py`)."""
    dtype = x.dtype if cfg.dtype is None else cfg.dtype
    x = x + layer_scale(p.get("ls1"), attend(layer_norm(p["norm1"], x, cfg.eps, dtype))).astype(x.dtype)
    h = mlp(p["mlp"], layer_norm(p["norm2"], x, cfg.eps, dtype))
    return x + layer_scale(p.get("ls2"), h).astype(x.dtype)


def project(p: Params, heads: jax.Array) -> jax.Array:
    """The attention's output projection: heads [..., H, D] -> rows [..., H*D]."""
    return linear(p["attn"]["proj"], heads.reshape(heads.shape[:-2] + (-1,)))


def self_attention(p: Params, cfg: BlockConfig, *tables: jax.Array):
    """The attention branch of rows attending among themselves: normalised rows
    [B, r, C] -> [B, r, C], with RoPE from `tables` (cos, sin [1|B, r, 1, D]) or none."""
    pos = RopeTables(*tables) if tables else None
    return lambda h: project(p, attention(*attention_qkv(p["attn"], h, cfg.num_heads, pos),
                                          implementation=cfg.kernel))


def attention_to(p: Params, cfg: BlockConfig, k: jax.Array, v: jax.Array, key_bias: jax.Array | None = None,
                 *tables: jax.Array):
    """The attention branch of a chunk of queries against given keys: normalised rows
    [B, r, C] (their RoPE rows in `tables`) -> [B, r, C], attending to K/V [B, Nk, H, D]
    (with `key_bias` [B, Nk])."""
    pos = RopeTables(*tables) if tables else None
    return lambda h: project(p, attention(attention_qkv(p["attn"], h, cfg.num_heads, pos, parts="q")[0], k, v,
                                          key_bias, implementation=cfg.kernel))


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


def chunked_block(p: Params, x: jax.Array, branch, inputs: tuple, cfg: BlockConfig) -> jax.Array:
    """`block` over chunks of tokens of a long sequence x [B, N, C], in place: chunk i's
    attention branch is `branch(*its rows of inputs)` (inputs chunked along tokens like
    x; e.g. its RoPE rows, or its rows of an attention computed beforehand)."""
    hidden = p["mlp"]["fc1"]["kernel"].shape[-1]
    return update_tokens(lambda xc, *ic: block(p, xc, branch(*ic), cfg), x, inputs,
                         bytes_per_row=x.shape[0] * hidden * 4)


def sequence_block(p: Params, x: jax.Array, pos: "jax.Array | RopeTables | None", cfg: BlockConfig) -> jax.Array:
    """`block` over B sequences x [B, N, C] -> [B, N, C], each token attending within its
    sequence; pos: RoPE tables [1|B, N, 1, D], integer positions [1|B, N, 2], or None.

    One in-place pass over the residual stream (`chunks.update_tokens`):
    - short sequences (frames, DINO images, the camera trunk): whole sequences per chunk;
    - long ones (a dense global block): K and V of the whole sequence first, then chunks
      of queries against all keys, each chunk finishing its rows (projection, residual,
      MLP). Only K and V ever exist for the whole sequence."""
    b, n, c = x.shape
    if pos is not None and not isinstance(pos, RopeTables):
        pos = RopeTables.from_positions(pos, c // cfg.num_heads, cfg.rope_freq)
    tables = () if pos is None else (pos.cos, pos.sin)
    per_sequence = n * p["mlp"]["fc1"]["kernel"].shape[-1] * 4  # one sequence's MLP hidden layer, float32
    if per_sequence <= chunks.TOKEN_CHUNK_BYTES:
        tables = tuple(map(chunks.whole, tables))
        if tables and tables[0].shape[0] == 1:  # shared positions: every chunk takes them whole
            shared = tables
            return update_tokens(lambda xc: block(p, xc, self_attention(p, cfg, *shared), cfg), x, axis=0,
                                 bytes_per_row=per_sequence, multiple=1)
        return update_tokens(lambda xc, *tc: block(p, xc, self_attention(p, cfg, *tc), cfg), x, tables, axis=0,
                             bytes_per_row=per_sequence, multiple=1)
    dtype = x.dtype if cfg.dtype is None else cfg.dtype
    x, (k, v) = chunks.map_tokens_through(block_qkv_rows(p, cfg.num_heads, cfg.eps, dtype, "kv"), x, tables,
                                          bytes_per_row=b * c * 4 * 2 + c * 4)
    return chunked_block(p, x, lambda *tc: attention_to(p, cfg, k, v, None, *tc), tables, cfg)


def dense_global_block(p_block: Params, x: jax.Array, pos, config, per_frame: int) -> jax.Array:
    """Upstream's global block: `sequence_block` over the whole sequence, each token
    attending to every token of every frame (RegimeVGGT's compressed global blocks are
    `rvggt_jax.compression.global_block`). x [B, N, C] (N = S * per_frame tokens of this device's
    frames); pos: the sequence's RoPE tables [1, N, 1, D] (or integer positions
    [1, N, 2]); config: the `VGGTConfig` (heads, RoPE, compute dtype). With the frames
    split over devices (`ops.shards.frame_layout`), its queries attend to every device's
    keys around the ring; padding frames are masked."""
    heads, dtype = config.num_heads, config.compute_dtype
    cfg = BlockConfig.of(config)
    b, n, c = x.shape
    layout = frame_layout(n // per_frame)
    if not layout.sharded:
        return sequence_block(p_block, x, pos, cfg)
    if not isinstance(pos, RopeTables):
        pos = RopeTables.from_positions(pos, c // heads, config.rope_freq)
    q, k, v = block_qkv(p_block, x, heads, pos, dtype=dtype)
    mask = None
    if layout.padded > layout.frames:
        real = layout.offset(per_frame) + jnp.arange(n) < layout.frames * per_frame
        mask = jnp.broadcast_to(jnp.where(real, 0.0, NEG_BIAS).astype(jnp.float32), (b, n))
    out = ring_attention(q, k, v, mask, layout, implementation=config.attention)
    # the block around the ring's output rows
    return chunked_block(p_block, x, lambda oc: lambda h: project(p_block, oc), (out,), cfg)


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


def block_stack(blocks: Params, indices, x: jax.Array, pos: "jax.Array | RopeTables | None", cfg: BlockConfig,
                remat: Any = None) -> jax.Array:
    """Apply numbered blocks `indices` (in order) with `lax.scan`; `remat`: how each block
    runs in a training step, a wrapper such as `jax.checkpoint` (`model.remat.checkpoint`
    under `VGGTConfig.remat`), or None."""
    def step(h, i):
        return sequence_block(select_block(blocks, indices, i), h, pos, cfg), None

    if remat is not None:
        step = remat(step)

    return jax.lax.scan(step, x, jnp.arange(len(indices)))[0]
