"""The per-forward compression state: what the global blocks share from one layer to the
next. A `State` (a pytree; geometry static) holds the protection flags (from
the DINOv2 [CLS] saliency Psi, or a stride), the band-aligned match cache {cache key:
`Match`} and the K/V slots of cached matches {(cache key, tile): `KVSlots`}.

    state = init_state(config.compression, saliency, geometry)   # once per forward
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.compression.config import CompressionConfig
from rvggt_jax.compression.kv import KVSlots
from rvggt_jax.compression.merge import Match, compact
from rvggt_jax.compression.partition import Geometry, partition, saliency_protect_count, stride_protected
from rvggt_jax.ops.shards import FrameShards, frame_layout


class State(NamedTuple):
    """The per-forward compression state (see the module docstring)."""

    geometry: Geometry  # static: frames, grid, special tokens
    protected: jax.Array | None  # [B, N] bool, the Psi- (or stride-) protected tokens (None without protection)
    protected_pos: jax.Array | None  # [B, P] int32, their positions
    matches: dict[str, Match]  # the band-aligned match cache
    kv: dict[tuple[str, tuple[int, int]], KVSlots]  # the dynamic K/V slots of cached matches

    @property
    def layout(self) -> FrameShards:
        """How the sequence's frames lie over devices in the program being traced."""
        return frame_layout(frames=self.geometry.frames)

    def with_match(self, key: str, match: Match) -> "State":
        return self._replace(matches={**self.matches, key: match})


def init_state(comp: CompressionConfig, saliency: jax.Array | None, geom: Geometry) -> State:
    """Per-forward state: protection flags from the saliency Psi [B, S, h*w] of every frame
    of the sequence.

    Protected patches of a frame s >= 1: its top max(1, floor(alpha*T)) patches under Psi
    (`lax.top_k`); with `protect="stride"` a fixed stride over the sequence (FastVGGT)."""
    frames, L, N = geom.frames, geom.per_frame, geom.tokens
    protected = protected_pos = None
    if comp.protect == "saliency":
        per_frame = saliency_protect_count(geom, comp.alpha)
        if saliency is None:
            raise ValueError("saliency protection needs the saliency Psi [B, S, h*w]")
        b = saliency.shape[0]
        if saliency.shape != (b, frames, geom.patches):
            raise ValueError(f"saliency must be [B, {frames}, {geom.patches}]; got {saliency.shape}")
        if per_frame > 0 and frames > 1:
            _, top = jax.lax.top_k(saliency[:, 1:].astype(jnp.float32), per_frame)  # [B, S-1, per_frame]
            offsets = (jnp.arange(1, frames, dtype=jnp.int32) * L + geom.num_special)[None, :, None]
            protected_pos = (top.astype(jnp.int32) + offsets).reshape(b, -1)
            protected = jnp.zeros((b, N), bool).at[jnp.arange(b)[:, None], protected_pos].set(True)
    elif comp.protect == "stride":
        b = 1 if saliency is None else saliency.shape[0]
        pos = stride_protected(N, comp.alpha)
        flags = np.zeros(N, bool)
        flags[pos] = True
        protected_pos = jnp.broadcast_to(jnp.asarray(pos, jnp.int32), (b, pos.size))
        protected = jnp.broadcast_to(jnp.asarray(flags), (b, N))
    if comp.duplicate_protected and protected_pos is not None:
        protected_pos = dst_first(protected_pos, partition(geom, comp.dst_seed).is_dst)
    return State(geom, protected, protected_pos, {}, {})


def dst_first(pos: jax.Array, is_dst: np.ndarray) -> jax.Array:
    """Positions pos [B, P] reordered, per row, dst first (each part in its order): the
    duplicated protected tokens' rows and slots beyond the layers' `n_dup` are then
    protected src (never a duplicate's row). `merge.compact`'s stable partition, no sort."""
    order, _ = compact(jnp.take(jnp.asarray(is_dst), pos, mode="clip"), pos.shape[1])
    return jnp.take_along_axis(pos, order, axis=1, mode="promise_in_bounds")
