"""The dense global block: upstream's Block over the whole sequence [B, S*P, C], each
token attending to every token of every frame. On one device it is `layers.sequence_block`; with
the frames split over devices, the keys travel around the devices (`ops.ring`).

RegimeVGGT's compressed global blocks are `rvggt_jax.compression.global_block`; the
aggregator calls this one for dense layers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvggt_jax.model import layers
from rvggt_jax.model.params import Params
from rvggt_jax.ops.attention import NEG_BIAS
from rvggt_jax.ops.ring import ring_attention
from rvggt_jax.ops.shards import FrameShards


def dense_global_block(p_block: Params, x: jax.Array, pos, config, shards: FrameShards | None = None,
                       per_frame: int = 0) -> jax.Array:
    """A dense global block over x [B, N, C] (N = S * per_frame tokens of this device's
    frames); pos: the sequence's RoPE tables [1, N, 1, D] (or integer positions
    [1, N, 2]); config: the `VGGTConfig` (heads, RoPE, compute dtype). Split over devices
    (`shards`), its queries attend to every device's keys around the ring; padding frames
    are masked."""
    heads, dtype = config.num_heads, config.compute_dtype
    cfg = layers.BlockConfig.of(config)
    if shards is None or not shards.sharded:
        return layers.sequence_block(p_block, x, pos, cfg)
    b, n, c = x.shape
    if not isinstance(pos, layers.RopeTables):
        pos = layers.RopeTables.from_positions(pos, c // heads, config.rope_freq)
    q, k, v = layers.block_qkv(p_block, x, heads, pos, dtype=dtype)
    mask = None
    if shards.padded > shards.frames:
        real = shards.offset(per_frame) + jnp.arange(n) < shards.frames * per_frame
        mask = jnp.broadcast_to(jnp.where(real, 0.0, NEG_BIAS).astype(jnp.float32), (b, n))
    out = ring_attention(q, k, v, mask, shards, implementation=config.attention)
    # the block around the ring's output rows
    return layers.chunked_block(p_block, x, lambda oc: lambda h: layers.project(p_block, oc), (out,), cfg)
