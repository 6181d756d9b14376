"""The alternating-attention aggregator: `depth` frame blocks interleaved with `depth`
global blocks over camera, register and patch tokens.

Frame blocks attend within each frame ([B*S, P, C]); global blocks attend across the
whole sequence ([B, S*P, C]) and are where RegimeVGGT compresses (`compression.global_block`).
"""

from __future__ import annotations

from typing import Iterable

import chex
import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax import compression, layers
from rvggt_jax.config import VGGTConfig
from rvggt_jax.layers import Params
from rvggt_jax.patch_embed import patch_embed


def special_tokens(token: jax.Array, b: int, s: int) -> jax.Array:
    """Upstream's first-frame/other-frames token pair [1, 2, X, C] -> [B*S, X, C]:
    frame 0 takes entry 0, every other frame entry 1."""
    first = jnp.broadcast_to(token[:, :1], (b, 1) + token.shape[2:])
    rest = jnp.broadcast_to(token[:, 1:2], (b, s - 1) + token.shape[2:])
    return jnp.concatenate([first, rest], axis=1).reshape((b * s,) + token.shape[2:])


def aggregator_forward(
    p: Params, images: jax.Array, config: VGGTConfig, keep_layers: Iterable[int]
) -> tuple[dict[int, jax.Array], jax.Array, jax.Array]:
    """images [B, S, 3, H, W] in [0, 1] ->
    (outputs {layer: [B, S, P, 2C]} for the layers in `keep_layers`,
     patch-embed tokens [B*S, h*w, C], saliency Psi [B, S, h*w]).

    Each output concatenates the frame-block and global-block outputs of that layer; the
    other layers' outputs are never materialised beyond their use."""
    b, s, _, hh, ww = images.shape
    ps = config.patch_size
    h, w = hh // ps, ww // ps
    c = config.embed_dim
    keep = set(keep_layers)

    patch_tokens, saliency = patch_embed(p["patch_embed"], images, config)
    tokens = jnp.concatenate(
        [special_tokens(p["camera_token"], b, s), special_tokens(p["register_token"], b, s), patch_tokens],
        axis=1,
    )
    num_tokens = tokens.shape[1]  # P = 1 + registers + h*w
    chex.assert_shape(tokens, (b * s, config.patch_start_idx + h * w, c))

    # RoPE tables, built once for all blocks: [1, P, 1, D] and [1, S*P, 1, D]
    frame_pos = layers.RopeTables.from_positions(
        jnp.asarray(layers.patch_positions(h, w, config.patch_start_idx))[None], config.head_dim, config.rope_freq)
    global_pos = jax.tree.map(lambda t: jnp.tile(t, (1, s, 1, 1)), frame_pos)

    if config.compression.is_dense:
        outputs = _dense_layers(p, tokens, frame_pos, global_pos, config, b, s, sorted(keep))
    else:
        outputs = _compressed_layers(p, tokens, frame_pos, global_pos, config, b, s, keep, saliency, (h, w))
    return outputs, patch_tokens, saliency


def _dense_layers(p, tokens, frame_pos, global_pos, config, b, s, keep):
    """All layers in one `lax.scan`: one compiled body instead of 2 * depth, which
    cuts compile time ~10x. The kept layers' frame and global halves go to two
    [K + 1, B, S, P, C] buffers; the other layers write to the spare slot K, so the body
    is the same unconditional in-place write for every layer (no select, no concat)."""
    n, num_tokens, c = tokens.shape
    spare = len(keep)
    slot = np.full(config.depth, spare, np.int32)
    slot[keep] = np.arange(len(keep))
    layer_ids = range(config.depth)
    xs = (jnp.arange(config.depth), jnp.asarray(slot))

    def layer(carry, xs_i):
        x, kept_frame, kept_global = carry
        i, k = xs_i
        p_frame = layers.select_block(p["frame_blocks"], layer_ids, i)
        p_global = layers.select_block(p["global_blocks"], layer_ids, i)
        x = layers.block(p_frame, x.reshape(b * s, num_tokens, c), config.num_heads, frame_pos, config.rope_freq)
        kept_frame = kept_frame.at[k].set(x.reshape(b, s, num_tokens, c))
        x = layers.block(p_global, x.reshape(b, s * num_tokens, c), config.num_heads, global_pos, config.rope_freq)
        kept_global = kept_global.at[k].set(x.reshape(b, s, num_tokens, c))
        return (x, kept_frame, kept_global), None

    buf = jnp.zeros((spare + 1, b, s, num_tokens, c), tokens.dtype)
    (_, kept_frame, kept_global), _ = jax.lax.scan(layer, (tokens.reshape(b, s * num_tokens, c), buf, buf), xs)
    return {i: jnp.concatenate([kept_frame[j], kept_global[j]], axis=-1) for j, i in enumerate(keep)}


def _compressed_layers(p, tokens, frame_pos, global_pos, config, b, s, keep, saliency, grid_hw):
    """Layers unrolled in Python: each compressed global block has its own static plan and
    the compression state may change structure between layers (band caches)."""
    n, num_tokens, c = tokens.shape
    state = compression.init_state(config, saliency, s, grid_hw)
    outputs: dict[int, jax.Array] = {}
    x = tokens
    for i in range(config.depth):
        x = layers.block(p["frame_blocks"][str(i)], x.reshape(b * s, num_tokens, c),
                         config.num_heads, frame_pos, config.rope_freq)
        frame_out = x
        x, state = compression.global_block(p["global_blocks"][str(i)], x.reshape(b, s * num_tokens, c),
                                            global_pos, i, config, state)
        if i in keep:
            outputs[i] = jnp.concatenate(
                [frame_out.reshape(b, s, num_tokens, c), x.reshape(b, s, num_tokens, c)], axis=-1
            )
    return outputs
