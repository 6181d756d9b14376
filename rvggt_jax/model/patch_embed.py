"""DINOv2 ViT/14 with registers: the patch embed of VGGT, and the [CLS] saliency Psi.

Psi (the RegimeVGGT saliency) is the [CLS] query's attention row in the last DINO block,
softmax with the 1/sqrt(d) scale, averaged over heads, patch entries only. It is read
off the q and k that block computes anyway.
"""

from __future__ import annotations

import functools
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.model import layers, remat
from rvggt_jax.ops.attention import attention
from rvggt_jax.ops import chunks
from rvggt_jax.ops.chunks import update_tokens
from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.layers import Params

# ImageNet statistics that upstream's aggregator normalises with before the patch embed.
RESNET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
RESNET_STD = np.array([0.229, 0.224, 0.225], np.float32)


# ---------------------------------------------------------------------------------------
# Position-embedding interpolation, equal to torch's antialiased bicubic.
# jax.image.resize uses the Keys kernel a=-0.5 *without* torch's support/normalisation
# rules and another kernel when not antialiasing, so we build torch's weight matrix.
# Shapes are static, so the matrices are numpy constants folded into the program.
# ---------------------------------------------------------------------------------------


def _cubic(x: np.ndarray, a: float) -> np.ndarray:
    x = np.abs(x)
    near = ((a + 2) * x - (a + 3)) * x * x + 1
    far = (((x - 5) * x + 8) * x - 4) * a
    return np.where(x < 1, near, np.where(x < 2, far, 0.0))


@functools.lru_cache(maxsize=64)
def bicubic_aa_matrix(in_size: int, out_size: int, scale: float | None = None) -> np.ndarray:
    """[out_size, in_size] weights of torch's `interpolate(mode="bicubic", antialias=True,
    align_corners=False)` along one axis. `scale` is input/output (defaults to the size
    ratio; torch passes 1/scale_factor when a scale factor is given)."""
    if in_size == out_size:
        # torch skips the pass along an axis whose size does not change, even when a
        # scale factor (interpolate_offset) would shift the sampling points.
        return np.eye(in_size, dtype=np.float32)
    scale = in_size / out_size if scale is None else scale
    # torch's antialiased kernels use the PIL cubic (a = -0.5) and widen it when shrinking.
    support = 2.0 * scale if scale >= 1.0 else 2.0
    inv = 1.0 / scale if scale >= 1.0 else 1.0
    m = np.zeros((out_size, in_size), np.float64)
    for i in range(out_size):
        center = scale * (i + 0.5)
        lo = max(int(center - support + 0.5), 0)
        hi = min(int(center + support + 0.5), in_size)
        j = np.arange(lo, hi)
        w = _cubic((j - center + 0.5) * inv, -0.5)
        m[i, lo:hi] = w / w.sum()
    return m.astype(np.float32)


def interpolate_pos_embed(pos_embed: jax.Array, h: int, w: int, offset: float = 0.0) -> jax.Array:
    """Resize the DINO position table to an h x w patch grid.

    pos_embed [1, 1 + M*M, C] -> [1, 1 + h*w, C] (class entry untouched)."""
    n = pos_embed.shape[1] - 1
    m = int(math.isqrt(n))
    if m * m != n:
        raise ValueError(f"pos_embed holds {n} patch entries, not a square grid")
    if h == m and w == m:
        return pos_embed
    cls_pos, grid = pos_embed[:, :1], pos_embed[0, 1:].reshape(m, m, -1)
    if offset:
        # upstream passes a scale factor (h + offset) / M, which torch turns back into a scale
        ry = bicubic_aa_matrix(m, h, m / (h + offset))
        rx = bicubic_aa_matrix(m, w, m / (w + offset))
    else:
        ry, rx = bicubic_aa_matrix(m, h), bicubic_aa_matrix(m, w)
    hp = jax.lax.Precision.HIGHEST
    grid = jnp.einsum("ym,mnc->ync", ry, grid, precision=hp)
    grid = jnp.einsum("xn,ync->yxc", rx, grid, precision=hp)
    return jnp.concatenate([cls_pos, grid.reshape(1, h * w, -1)], axis=1)


# ---------------------------------------------------------------------------------------
# The ViT
# ---------------------------------------------------------------------------------------


def patchify(p: Params, images: jax.Array, patch: int) -> jax.Array:
    """The stride-`patch` convolution as a matmul: images [N, 3, H, W] -> [N, h*w, C]."""
    n, c, hh, ww = images.shape
    h, w = hh // patch, ww // patch
    # each patch flattened channel-major (c, kh, kw), as torch's OIHW weight is: the copy
    # then moves runs of `patch` contiguous pixels (a channel-last order moves single
    # floats, ~1.5x slower for 64 frames of 168 x 224 on a 2-core CPU)
    x = images.reshape(n, c, h, patch, w, patch).transpose(0, 2, 4, 1, 3, 5)
    x = x.reshape(n, h * w, c * patch * patch)
    kernel = p["kernel"].transpose(2, 0, 1, 3).reshape(c * patch * patch, -1)  # HWIO -> (c, kh, kw) x O
    return layers.linear({"kernel": kernel, "bias": p["bias"]}, x)


def cls_saliency(q: jax.Array, k: jax.Array, num_prefix: int) -> jax.Array:
    """Psi: softmax of the [CLS] query (token 0) over all keys, head-averaged, patch
    entries only. q, k [N, L, H, D] -> [N, L - num_prefix]."""
    scale = 1.0 / math.sqrt(q.shape[-1])
    logits = jnp.einsum("nhd,nkhd->nhk", q[:, 0] * jnp.asarray(scale, q.dtype), k,
                        preferred_element_type=jnp.float32)
    return jax.nn.softmax(logits, axis=-1).mean(axis=1)[:, num_prefix:]


UNIT_OF_UINT8 = np.arange(256, dtype=np.float32) / np.float32(255.0)  # [256]: v -> v / 255


def unit_images(images: jax.Array) -> jax.Array:
    """Images as `check_images` returns them -> float32 in [0, 1]: uint8 / 255 in
    float32, the same division upstream's ToTensor (and `load_images`) does, so a uint8
    input gives bit for bit the outputs of its float32 form."""
    if images.dtype == jnp.uint8:
        # a table of the 256 quotients, divided on the host: a compiled division by a
        # constant becomes a multiplication by its reciprocal, which rounds 1 in ~3
        # values differently
        return jnp.asarray(UNIT_OF_UINT8)[images]
    return images


def embed_images(p: Params, images: jax.Array, config: VGGTConfig) -> jax.Array:
    """The ViT's input tokens: images [N, 3, H, W] (float in [0, 1] or uint8) ->
    [N, 1 + R + h*w, C] float32 ([CLS] + position, R registers, patches + positions).

    A chunk of whole images at a time, written into the token buffer: the normalised
    images, their patch matrix and the unpadded patch tokens exist for one chunk only.
    (Whole, a TPU lays the patch matrix out with its 3 channels minor, padded to a tile:
    11 GiB at 1000 frames of 392 x 518.)"""
    dino = config.dino
    dtype = config.compute_dtype
    ps = config.patch_size
    n, c, hh, ww = images.shape
    h, w = hh // ps, ww // ps
    width = config.embed_dim
    pos = interpolate_pos_embed(p["pos_embed"].astype(jnp.float32), h, w, dino.interpolate_offset)
    regs = p["register_tokens"].astype(jnp.float32)

    def embed(chunk):  # [n_c, 3, H, W] -> [n_c, 1 + R + h*w, C]
        m = chunk.shape[0]
        x = (unit_images(chunk) - RESNET_MEAN[:, None, None]) / RESNET_STD[:, None, None]
        x = patchify(p["patch_embed"]["proj"], x.astype(dtype), ps).astype(jnp.float32)
        x = jnp.concatenate([jnp.broadcast_to(p["cls_token"].astype(jnp.float32), (m, 1, width)), x], axis=1) + pos
        return jnp.concatenate([x[:, :1], jnp.broadcast_to(regs, (m,) + regs.shape[1:]), x[:, 1:]], axis=1)

    tokens = 1 + regs.shape[1] + h * w
    # per image: the float32 input, its patch matrix and the tokens (twice, the concats)
    per_image = c * hh * ww * 4 * 2 + tokens * width * 4 * 3
    return chunks.map_tokens(embed, (images,), axis=0, bytes_per_row=per_image, multiple=1)


def dino_tokens(p: Params, images: jax.Array, config: VGGTConfig) -> tuple[jax.Array, int, jax.Array]:
    """DINOv2 forward on images [N, 3, H, W] (float in [0, 1] or uint8; normalised with
    ImageNet's mean and std inside, `embed_images`), its blocks in
    `config.compute_dtype` (the residual stream in float32, as under torch's autocast).

    -> (every token after the final norm [N, 1 + R + h*w, C] float32 ([CLS], R
    registers, patches), the prefix length 1 + R, saliency Psi [N, h*w] float32).
    The final norm is applied in place: the aggregator overwrites the prefix with its own
    camera and register tokens in the same buffer."""
    dino = config.dino
    dtype = config.compute_dtype
    ps = config.patch_size
    n, _, hh, ww = images.shape
    h, w = hh // ps, ww // ps
    eps = dino.layer_norm_eps

    x = embed_images(p, images, config)
    num_prefix = 1 + p["register_tokens"].shape[1]

    depth = dino.depth
    cfg = layers.BlockConfig(dino.num_heads, eps, dtype, kernel=config.attention)
    if depth > 1:
        x = layers.block_stack(p["blocks"], range(depth - 1), x, None, cfg,
                               remat=lambda f: remat.checkpoint(f, config, "block"))

    # The last block also gives the saliency, read off the q and k its attention computes
    # anyway; whole images per chunk, like every block.
    blk = p["blocks"][str(depth - 1)]

    def last_block(xc):
        saliency = []  # (the branch's second result, from the same trace)

        def attend(h):
            q, k, v = layers.attention_qkv(blk["attn"], h, dino.num_heads)
            saliency.append(cls_saliency(q, k, num_prefix))
            return layers.project(blk, attention(q, k, v, implementation=cfg.kernel))

        return layers.block(blk, xc, attend, cfg), saliency[0]

    hidden = blk["mlp"]["fc1"]["kernel"].shape[-1]
    x, saliency = chunks.map_tokens(last_block, (x,), axis=0, bytes_per_row=x.shape[1] * hidden * 4, multiple=1)

    c = x.shape[-1]
    x = update_tokens(lambda xc: layers.layer_norm(p["norm"], xc, eps, jnp.float32), x.reshape(1, -1, c),
                      bytes_per_row=c * 4 * 2).reshape(x.shape)
    chex.assert_shape(x, (n, num_prefix + h * w, config.embed_dim))
    chex.assert_shape(saliency, (n, h * w))
    return x, num_prefix, saliency


def patch_embed(p: Params, images: jax.Array, config: VGGTConfig) -> tuple[jax.Array, jax.Array]:
    """images [B, S, 3, H, W] in [0, 1] -> (patch tokens [B*S, h*w, C], Psi [B, S, h*w])."""
    x, num_prefix, saliency = patch_embed_tokens(p, images, config)
    return x[:, num_prefix:], saliency


def patch_embed_tokens(p: Params, images: jax.Array, config: VGGTConfig) -> tuple[jax.Array, int, jax.Array]:
    """images [B, S, 3, H, W] (float in [0, 1] or uint8, `inputs.check_images`) ->
    (DINO tokens [B*S, 1 + R + h*w, C] with the patch tokens after the prefix of 1 + R,
    the prefix length, Psi [B, S, h*w])."""
    b, s, c, hh, ww = images.shape
    num_prefix = 1 + p["register_tokens"].shape[1]

    def dino(p, images):
        tokens, _, saliency = dino_tokens(p, images, config)
        return tokens, saliency

    # a training step under remat "full" keeps the images alone: the whole DINOv2 forward is
    # recomputed for its backward pass (config.remat)
    tokens, saliency = remat.checkpoint(dino, config, "patch_embed")(p, images.reshape(b * s, c, hh, ww))
    return tokens, num_prefix, saliency.reshape(b, s, -1)
