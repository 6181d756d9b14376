"""Where the frames of a forward pass live: all on one device, or split over a mesh axis.

    shards = FrameShards.single(frames)                 # one device: every op below is local
    shards = FrameShards(frames, devices=4)             # inside shard_map over axis "frames"

    with split_frames(shards):                          # parallel/, inside its shard_map
        out = forward_frames(params, images, config)    # the model asks frame_layout(S)

The model never takes the layout as an argument: `parallel/` (and the sharded train
step) enter `split_frames` inside the body of their `shard_map`, and each model function
that crosses frames asks `frame_layout(frames_here)` while it is traced. The layout is
static (it shapes the program, like the mesh), so it belongs to the trace, not to the
data; outside a split every frame is on this device.

Device d holds frames [d * local, (d + 1) * local) of the sequence padded to
`devices * local` frames (the padding frames are zeros, at the end, and never reach a
real token: every cross-frame op below drops them). The forward pass is one program for
every device (`jax.shard_map`); the methods here are its only cross-device steps, each a
JAX collective over `axis` (all-gather, psum, permutes around the ring of devices), and
each the identity (or a plain local op) on one device, so the single-device forward runs
the same code.

Token-level methods take `per_frame` (tokens per frame, L): the global blocks flatten
frames x tokens into one axis of `frames * L` rows.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from dataclasses import dataclass
from typing import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops import chunks
from rvggt_jax.ops.bits import moved  # (collectives that only move values: 16-bit floats as bits)
from rvggt_jax.ops.ordering import zeros_after

FRAMES_AXIS = "frames"


@dataclass(frozen=True)
class FrameShards:
    """`frames` real frames over `devices` devices of mesh axis `axis` (None: one device)."""

    frames: int
    devices: int = 1
    axis: str | None = None

    @classmethod
    def single(cls, frames: int) -> "FrameShards":
        return cls(frames, 1, None)

    def __post_init__(self):
        if self.frames < 1 or self.devices < 1:
            raise ValueError(f"FrameShards needs frames >= 1 and devices >= 1; got {self.frames}, {self.devices}")
        if (self.devices > 1) != (self.axis is not None):
            raise ValueError("a mesh axis name is needed exactly when there is more than one device")

    @property
    def sharded(self) -> bool:
        return self.axis is not None

    @property
    def local(self) -> int:
        """Frames per device."""
        return math.ceil(self.frames / self.devices)

    @property
    def padded(self) -> int:
        """Frames of the padded sequence (`devices * local`)."""
        return self.local * self.devices

    # ---- where this device sits ------------------------------------------------------

    def index(self) -> jax.Array | int:
        return jax.lax.axis_index(self.axis) if self.sharded else 0

    def offset(self, per_frame: int = 1) -> jax.Array | int:
        """Global index of this device's first frame (x per_frame: its first token)."""
        return self.index() * (self.local * per_frame)

    def frame_ids(self) -> jax.Array:
        """[local] global frame index of every local frame."""
        return self.offset() + jnp.arange(self.local, dtype=jnp.int32)

    def per_device(self, table: np.ndarray) -> jax.Array:
        """Row `index()` of a static [devices, ...] table (one row per device)."""
        if not self.sharded:
            return jnp.asarray(table[0])
        return chunks.dynamic_index(jnp.asarray(table), self.index(), 0)

    # ---- frames ----------------------------------------------------------------------

    def gather(self, x: jax.Array, axis: int, per_frame: int = 1) -> jax.Array:
        """Local frames (x per_frame rows) along `axis` -> the real frames of every
        device: [.., local * L, ..] -> [.., frames * L, ..] (an all-gather)."""
        if not self.sharded:
            return x
        full = jax.lax.all_gather(x, self.axis, axis=axis, tiled=True)
        return jax.lax.slice_in_dim(full, 0, self.frames * per_frame, axis=axis)

    def local_part(self, x: jax.Array, axis: int, per_frame: int = 1, pad_value=0) -> jax.Array:
        """This device's frames of an array over every real frame: [.., frames * L, ..] ->
        [.., local * L, ..] (padding frames filled with `pad_value`)."""
        if not self.sharded:
            return x
        extra = (self.padded - self.frames) * per_frame
        if extra:
            widths = [(0, 0)] * x.ndim
            widths[axis] = (0, extra)
            x = jnp.pad(x, widths, constant_values=pad_value)
        return jax.lax.dynamic_slice_in_dim(x, self.offset(per_frame), self.local * per_frame, axis=axis)

    def first(self, x: jax.Array, axis: int) -> jax.Array:
        """Global frame 0 of x (local frames along `axis`), on every device."""
        x0 = jnp.take(x, 0, axis=axis)
        if not self.sharded:
            return x0
        return jax.lax.psum(jnp.where(self.index() == 0, x0, jnp.zeros_like(x0)), self.axis)

    # ---- tokens ----------------------------------------------------------------------

    def take_rows(self, x: jax.Array, idx: jax.Array, per_frame: int) -> jax.Array:
        """Rows idx [B, M] (global token positions) of the sequence whose local rows are
        x [B, local * L, ...], on every device: [B, M, ...]. Each row comes from the
        device that holds it (a psum of one non-zero term: exact)."""
        if not self.sharded:
            return chunks.take_along(x, idx, axis=1)
        start = self.offset(per_frame)
        n_local = x.shape[1]

        def mine(ic):
            rel = ic - start
            got = chunks.take_along(x, jnp.clip(rel, 0, n_local - 1), axis=1)
            held = ((rel >= 0) & (rel < n_local)).reshape(ic.shape + (1,) * (got.ndim - 2))
            return jnp.where(held, got, jnp.zeros_like(got))

        # in chunks of rows: the gathered rows never exist for all of idx at once, only
        # the result
        per_row = idx.shape[0] * math.prod(x.shape[2:]) * 4 * 3
        # (16-bit floats summed as bits: exact, the other devices add 0, and XLA:CPU
        # would move a bfloat16 all-reduce in float32)
        return moved(lambda t: jax.lax.psum(t, self.axis), chunks.map_tokens(mine, (idx,), bytes_per_row=per_row,
                                                                              dep=x))

    def local_positions(self, positions: np.ndarray, per_frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Split static global token positions [M] (ascending) over the devices:
        (table [devices, M_max] of local row indices (padded with 0), order [M]: where
        each position lands in the [devices * M_max] concatenation of the devices'
        results). For gathering per-device results back into the global order."""
        positions = np.asarray(positions)
        rows = self.local * per_frame
        owner = positions // rows
        counts = np.bincount(owner, minlength=self.devices)
        m_max = max(1, int(counts.max()) if counts.size else 1)
        table = np.zeros((self.devices, m_max), np.int64)
        order = np.empty(positions.size, np.int64)
        for d in range(self.devices):
            mine = np.flatnonzero(owner == d)
            table[d, :mine.size] = positions[mine] - d * rows
            order[mine] = d * m_max + np.arange(mine.size)
        return table, order

    def gather_results(self, y: jax.Array, order: np.ndarray, axis: int = 1) -> jax.Array:
        """Per-device results y [.., M_max, ..] along `axis` -> the global order [.., M, ..]
        (`order` from `local_positions`): an all-gather."""
        full = jax.lax.all_gather(y, self.axis, axis=axis, tiled=True)
        return jnp.take(full, jnp.asarray(order, jnp.int32), axis=axis, mode="clip")

    # ---- rings: one neighbour's share at a time ---------------------------------------

    def ring_shift(self, tree):
        """Every device's arrays to the next device (d -> d + 1 mod devices)."""
        n = self.devices
        pairs = [(i, (i + 1) % n) for i in range(n)]

        def shift(a):
            return moved(lambda t: jax.lax.ppermute(t, self.axis, pairs), a)

        return jax.tree.map(shift, tree)

    def ring_sum_scatter(self, contribution: Callable[[jax.Array, jax.Array | None], jax.Array]) -> jax.Array:
        """Sum over devices of this device's part of each block of an axis split in
        `devices` blocks, each device ending with the sum of its own block:
        `contribution(block, acc)` adds this device's part of block `block` to `acc`
        (None: to zeros), in place where it can. A reduce-scatter whose blocks are made
        one at a time (the running sum travels around the devices, each adding its part
        into the sum it received), so no device ever holds more than two blocks. One
        device: contribution(0, None)."""
        if not self.sharded:
            return contribution(0, None)
        n, d = self.devices, self.index()

        # step t: add this device's part of block (d - t - 1) mod n to the sum received
        # for it; after n - 1 steps that block is d, summed over every device
        def step(t, acc):
            return contribution((d - t - 1) % n, self.ring_shift(acc))

        return jax.lax.fori_loop(1, n, step, contribution((d - 1) % n, None))

    def ring_take(self, blocks: jax.Array, idx: jax.Array) -> jax.Array:
        """Rows idx [B, M] (global indices) of an axis split in blocks of R rows per
        device (this device's block: blocks [B, R, ...]) -> [B, M, ...]: the blocks travel
        around the devices, each row taken when its block passes."""
        if not self.sharded:
            return chunks.take_along(blocks, idx, axis=1)
        n, d, r = self.devices, self.index(), blocks.shape[1]

        def take(owner, blk, acc):
            rel = idx - owner * r
            got = chunks.take_along(blk, jnp.clip(rel, 0, r - 1), axis=1)
            mine = ((rel >= 0) & (rel < r)).reshape(idx.shape + (1,) * (blk.ndim - 2))
            return jnp.where(mine, got, acc)

        def step(t, carry):
            blk, acc = carry
            blk = self.ring_shift(blk)
            return blk, take((d - t) % n, blk, acc)

        first = take(d, blocks, zeros_after(idx.shape + blocks.shape[2:], blocks.dtype, blocks))
        return jax.lax.fori_loop(1, n, step, (blocks, first))[1]

    def share(self, n: int) -> int:
        """Rows per device when `n` rows are split evenly (n rounded up)."""
        return math.ceil(n / self.devices)


jax.tree_util.register_static(FrameShards)


_SPLIT: contextvars.ContextVar[FrameShards | None] = contextvars.ContextVar("rvggt_frame_split", default=None)


@contextlib.contextmanager
def split_frames(shards: FrameShards) -> Iterator[FrameShards]:
    """Trace the model inside with its frames laid out as `shards` (entered inside the
    body of a `jax.shard_map` over `shards.axis`, so that the body is traced under it
    whenever JAX traces it). Read at trace time only: a `jax.jit` nested inside the model
    would key its cache without it, so the model's code nests none, and a custom VJP's
    backward (traced after the block) gets the layout as an argument from its forward."""
    token = _SPLIT.set(shards)
    try:
        yield shards
    finally:
        _SPLIT.reset(token)


def frame_layout(local: int | None = None, *, frames: int | None = None) -> FrameShards:
    """How the frames of the program being traced lie: the split entered by
    `split_frames`, or else all of them on this device. Give this device's frame count
    (`local`) or the sequence's (`frames`); a split that disagrees is an error, not a
    silent single-device program."""
    split = _SPLIT.get()
    if split is None:
        n = local if local is not None else frames
        if n is None:
            raise ValueError("frame_layout needs this device's frame count or the sequence's")
        return FrameShards.single(n)
    if local is not None and local != split.local:
        raise ValueError(f"{local} frames on this device, but the frames are split as {split.frames} over "
                         f"{split.devices} devices ({split.local} a device)")
    if frames is not None and frames != split.frames:
        raise ValueError(f"a sequence of {frames} frames, but the split is of {split.frames}")
    return split
