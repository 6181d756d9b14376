"""RegimeVGGT's global block: one global block under the configured compression.

    state = state.init_state(config.compression, saliency, geometry)   # once per forward
    x, state = global_block(p_block, x, pos, layer, config, state)

`layer` is a Python int: every layer has its own static plan (`plan.layer_plan`) and the
state may gain entries (the band caches) from one layer to the next. The plan's kind
picks the block: dense (`model.layers.dense_global_block`), within frames, K/V-downsampled
(`kv_layer.kv_block`) or merging (`merged_layer.merging_block`). Nothing branches on
data: every shape comes from (x.shape, geometry, configuration), and the blocks check
their attention's shapes against the plan at trace time, so the plan (what `cost.py`
and the tests read) is what runs.

Split over devices (`FrameShards`), x holds this device's frames and the state is
sequence-wide on every device. What a layer exchanges: dense, every device's K and V
around the ring (`ops.ring`); K/V downsampling, the kept tokens' rows (one psum);
merging, see `merged_layer`. See docs/sharding.md.
"""

from __future__ import annotations

import jax

from rvggt_jax.compression.config import LayerKind
from rvggt_jax.compression.kv_layer import kv_block
from rvggt_jax.compression.merged_layer import merging_block
from rvggt_jax.compression.plan import layer_plan
from rvggt_jax.compression.state import State
from rvggt_jax.model import layers
from rvggt_jax.model.params import Params


def global_block(p_block: Params, x: jax.Array, pos, layer: int, config, state: State) -> tuple[jax.Array, State]:
    """One global block under the configured compression.

    p_block: one upstream Block's params; x [B, N, C] (the float32 residual stream),
    N = S*P; pos: the sequence's RoPE tables [1, N, 1, D] (or integer positions
    [1, N, 2]); layer: the global layer index (Python int); config: the `VGGTConfig`
    (heads, RoPE, compute dtype, compression). Attention and MLP run in
    `config.compute_dtype`. Returns (x [B, N, C], state), the state with this layer's
    match (and K/V slots) cached when its plan stores them.
    """
    geom, layout = state.geometry, state.layout
    plan = layer_plan(config.compression, layer, geom)
    L = geom.per_frame
    b, n, c = x.shape
    if n != layout.local * L:
        raise ValueError(f"global block {layer}: {n} tokens but the state describes {layout.local * L}")

    if plan.kind == LayerKind.DENSE:
        return layers.dense_global_block(p_block, x, pos, config, L), state
    if plan.kind == LayerKind.FRAME:
        frame_pos = pos.first(L) if isinstance(pos, layers.RopeTables) else pos[:, :L]
        out = layers.sequence_block(p_block, x.reshape(b * layout.local, L, c), frame_pos,
                                    layers.BlockConfig.of(config))
        return out.reshape(b, n, c), state
    if not isinstance(pos, layers.RopeTables):
        pos = layers.RopeTables.from_positions(pos, c // config.num_heads, config.rope_freq)
    if plan.kind == LayerKind.KV:
        return kv_block(p_block, x, pos, plan, config, state), state
    return merging_block(p_block, x, pos, plan, config, state)
