"""Phase-shifted K/V sub-grid on the merged tokens: static slot bounds, dynamic slots and
masks.

A merged token is kept as a key/value when its parent position (its dst, or itself if
unmerged) is kept by `partition.kv_static_keep` (camera/register token, frame-0 anchor,
phase-shifted sub-grid) or, in the paper variant, Psi-protected. The dst part of the
query layout has static parents, so its kept slots are static indices
(`plan.fixed_kv_index`); the unmerged src are data-dependent, so they fill `n_dyn`
slots by compaction (kept candidates first), the rest masked.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.compression.config import CompressionConfig, LayerKind
from rvggt_jax.compression.merge import Match, compact
from rvggt_jax.compression.plan import LayerPlan


class KVSlots(NamedTuple):
    """The data-dependent K/V slots of a layer (a pytree)."""

    index: jax.Array  # [B, n_dyn] int32 indices into the query layout
    valid: jax.Array  # [B, n_dyn] bool: the slot is filled


def dynamic_slots(plan: LayerPlan, comp: CompressionConfig, match: Match | None,
                  protected: jax.Array | None) -> KVSlots:
    """The data-dependent K/V slots of a layer (its static mask `plan.kv_keep`, its
    partition `plan.partition`).

    protected: [B, N] bool Psi-protection flags (only read when the plan keeps protected
    tokens in K/V)."""
    keep_np = plan.kv_keep
    keep_protected = comp.kv_protect_saliency and protected is not None
    if plan.kind == LayerKind.KV:
        # Identity layout: candidates are the positions not kept statically.
        cand = np.flatnonzero(~keep_np)
        valid = jnp.take(protected, cand, axis=1, mode="clip")
        idx, ok = compact(valid, plan.n_dyn)
        return KVSlots(jnp.take(jnp.asarray(cand, jnp.int32), idx, mode="clip"), ok)
    unm_pos = match.unm_pos  # [B, U]
    valid = jnp.take(jnp.asarray(keep_np), unm_pos, mode="clip")
    if plan.r_max > plan.r:  # (a row whose src merged beyond the static r is empty)
        valid = valid & (match.sizes[:, plan.n_dst:] > 0)
    if keep_protected:
        valid = valid | jnp.take_along_axis(protected, unm_pos, axis=1, mode="promise_in_bounds")
    cand = plan.n_dst + jnp.broadcast_to(jnp.arange(plan.n_unm, dtype=jnp.int32), unm_pos.shape)
    if keep_protected:
        dst_pos = plan.partition.dst_pos
        dst_not_kept = np.flatnonzero(~keep_np[dst_pos])  # indices into the dst part
        valid = jnp.concatenate([jnp.take(protected, dst_pos[dst_not_kept], axis=1, mode="clip"), valid], axis=1)
        cand = jnp.concatenate([jnp.broadcast_to(jnp.asarray(dst_not_kept, jnp.int32),
                                                 (cand.shape[0], dst_not_kept.size)), cand], axis=1)
    idx, ok = compact(valid, plan.n_dyn)
    return KVSlots(jnp.take_along_axis(cand, idx, axis=1, mode="promise_in_bounds"), ok)
