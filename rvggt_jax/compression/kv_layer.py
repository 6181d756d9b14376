"""A K/V-downsampled global block: every query, keys and values of the kept tokens only
(a fixed sub-grid with a phase offset per frame, the frame-0 anchor and the special
tokens, plus the dynamic slots of the protected tokens).

K and V are projected for the kept tokens only (projection, qk-norm and RoPE are per
token, so selecting before projecting is exact), then Q chunk by chunk, each chunk
attending and finishing its rows: no full-sequence Q, K or V.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvggt_jax.compression import kv as kv_lib
from rvggt_jax.compression.plan import LayerPlan, check_shapes
from rvggt_jax.compression.state import State
from rvggt_jax.model import layers
from rvggt_jax.model.params import Params
from rvggt_jax.ops.attention import log_sizes
from rvggt_jax.ops.shards import frame_layout


def kv_block(p_block: Params, x: jax.Array, pos: layers.RopeTables, plan: LayerPlan, config, state: State
             ) -> jax.Array:
    """One K/V-downsampled global block over x [B, N, C] (this device's frames; pos:
    their RoPE tables) -> x [B, N, C]."""
    comp = config.compression
    b = x.shape[0]
    fixed = plan.fixed_kv
    sel = jnp.broadcast_to(jnp.asarray(fixed, jnp.int32), (b, fixed.size))
    log_g = None
    if plan.n_dyn:
        idx, ok = kv_lib.dynamic_slots(plan, comp, None, state.protected)
        sel = jnp.concatenate([sel, idx], axis=1)
        valid = jnp.concatenate([jnp.ones((b, fixed.size), bool), ok], axis=1)
        log_g = log_sizes(jnp.ones(valid.shape, jnp.float32), valid)
    kk, vv = rows_kv(p_block, x, sel, pos, config, plan)
    # (the plan counts the whole sequence's queries; x holds this device's frames)
    check_shapes(plan, comp, x.shape[1] // state.layout.local * plan.frames, kk, log_g)
    cfg = layers.BlockConfig.of(config)
    return layers.chunked_block(p_block, x, lambda *tc: layers.attention_to(p_block, cfg, kk, vv, log_g, *tc),
                                (pos.cos, pos.sin), cfg)


def rows_kv(p_block: Params, x: jax.Array, idx: jax.Array, pos: layers.RopeTables, config, plan: LayerPlan,
            num_heads: int | None = None) -> tuple[jax.Array, jax.Array]:
    """K and V [B, M, H, d] of the tokens idx [B, M] (global positions) of the sequence
    whose rows x [B, N, C] this device holds (their norm1, projection, qk-norm and RoPE
    at their own positions; `pos` the tables of x's tokens, which repeat every frame).
    num_heads: the heads p_block's projections make (default all; a head group's fewer)."""
    per_frame = plan.per_frame
    rows = frame_layout(frames=plan.frames).take_rows(x, idx, per_frame)
    tables = pos.frame_rows(idx % per_frame)
    heads = config.num_heads if num_heads is None else num_heads
    return layers.block_qkv(p_block, rows, heads, tables, dtype=config.compute_dtype, parts="kv")
