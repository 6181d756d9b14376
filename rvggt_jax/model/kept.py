"""The aggregator layers the heads read (`KeptLayer`), and the stacked buffers that hold
them while the aggregator runs: every layer writes its frame and global halves to a slot
(`kept_slots`), so the layer loop's body is the same unconditional in-place write for
every layer.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.bits import Bits16, read_buffer
from rvggt_jax.ops.ordering import zeros_from


@jax.tree_util.register_pytree_node_class
class KeptLayer:
    """The tokens of one kept aggregator layer, [B, S, P, 2C] float32 on demand, without a
    copy: what the heads take. Its frame-block and global-block halves stay where the
    aggregator left them and are sliced and concatenated per group of frames where a head
    reads them (`frames`, `token`; `array` is the whole layer, a copy).

    Each half is a slot of a stacked [K, B, S, P, C] buffer (compute dtype; 16-bit ones as
    `bits.Bits16`): the frame half in slot `slot`, the global half in `global_slot`
    (default the same). The last layer's global half is the aggregator's final residual
    stream itself ([1, B, S, P, C] float32, slot 0), read rounded to `dtype` (the compute
    dtype), the values its slot would have held. `KeptLayer.of(tokens)` wraps a plain
    [B, S, P, 2C] array (golden outputs, tests)."""

    def __init__(self, frame_buf, global_buf, slot: int, global_slot: int | None = None, dtype=None):
        self.frame_buf, self.global_buf, self.slot = frame_buf, global_buf, slot
        self.global_slot = slot if global_slot is None else global_slot
        self.dtype = None if dtype is None else jnp.dtype(dtype)

    @classmethod
    def of(cls, tokens: jax.Array) -> "KeptLayer":
        """A plain [B, S, P, 2C] array as a kept layer (its halves in one slot each)."""
        c = tokens.shape[-1] // 2
        return cls(tokens[None, ..., :c], tokens[None, ..., c:], 0)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.frame_buf.shape[1:-1] + (2 * self.frame_buf.shape[-1],)

    @property
    def ndim(self) -> int:
        return 4

    def _read(self, op, *index) -> jax.Array:
        """op(buffer, slot, *index) on both halves, concatenated along channels, float32."""
        halves = [read_buffer(self.frame_buf, lambda b, *i: op(b, self.slot, *i), *index),
                  read_buffer(self.global_buf, lambda b, *i: op(b, self.global_slot, *i), *index)]
        if self.dtype is not None:  # (the residual stream, as its slot would hold it)
            halves = [halves[0].astype(jnp.float32), rounded(halves[1], self.dtype)]
        # (the barrier keeps the float32 cast on the slices)
        return jnp.concatenate(jax.lax.optimization_barrier(halves), axis=-1).astype(jnp.float32)

    def frames(self, start: jax.Array | int, count: int) -> jax.Array:
        """Frames [start, start + count) of the flattened B*S frames: [count, P, 2C] float32."""
        def part(buf, slot, start):
            # (buf: float32, or a 16-bit buffer's bits; plain slices, which also carry
            # the derivatives of `bits.Bits16`)
            flat = buf.reshape((buf.shape[0], -1) + buf.shape[3:])  # [K, B*S, P, C]
            # Frames first, then the slot, both dynamic slices (a static slot slice is
            # loop-invariant: XLA would hoist it, cast to float32, out of the heads' loop)
            frames = jax.lax.dynamic_slice_in_dim(flat, start, count, 1)
            return jax.lax.dynamic_index_in_dim(frames, slot, 0, keepdims=False)

        return self._read(part, start)

    def token(self, index: int) -> jax.Array:
        """One token of every frame: [B, S, 2C] float32 (index 0: the camera token).
        Read as the block of 8 tokens that holds it, then indexed: a single token of every
        frame is one row of each of XLA:TPU's (8, 128) tiles, and XLA:TPU served that
        slice by re-laying out the whole kept buffer (an 8.5 GB copy at 1000 frames)."""
        lo = (index // 8) * 8
        hi = min(lo + 8, self.frame_buf.shape[3])
        return self._read(lambda buf, slot: buf[slot, :, :, lo:hi])[:, :, index - lo]

    def array(self) -> jax.Array:
        """The whole layer [B, S, P, 2C] float32 (a copy)."""
        return self._read(lambda buf, slot: buf[slot])

    def tree_flatten(self):
        return (self.frame_buf, self.global_buf), (self.slot, self.global_slot, self.dtype)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children, *aux)


def rounded(x: jax.Array, dtype) -> jax.Array:
    """float32 x rounded to `dtype`'s precision, still float32. bfloat16 by its bits
    (round to nearest even on the upper 16 bits): a cast would let XLA:TPU's bfloat16
    propagation turn the stream it slices into bfloat16 whole, a 2 GB copy at 1000
    frames (and another for its re-layout)."""
    if jnp.dtype(dtype) != jnp.dtype(jnp.bfloat16):
        return x.astype(dtype).astype(jnp.float32)
    bits = jax.lax.bitcast_convert_type(x.astype(jnp.float32), jnp.uint32)
    bits = (bits + jnp.uint32(0x7FFF) + ((bits >> 16) & 1)) & jnp.uint32(0xFFFF0000)
    return jnp.where(jnp.isnan(x), x, jax.lax.bitcast_convert_type(bits, jnp.float32))


def kept_slots(depth: int, keep) -> tuple[np.ndarray, int]:
    """(slot [depth] of every layer's outputs, number of spare slots). Kept layer keep[j]
    owns slot j; any other layer writes to the slot of the next kept layer, which that
    layer overwrites later in the same loop. Only layers after the last kept one need a
    spare slot (K + 1)."""
    keep = sorted(keep)
    slot = np.zeros(depth, np.int32)
    spare = int(not keep or keep[-1] < depth - 1)
    for i in range(depth):
        later = [j for j, k in enumerate(keep) if k >= i]
        slot[i] = later[0] if later else len(keep)
    return slot, spare


def kept_buffer(shape: tuple[int, ...], dtype, dep: jax.Array):
    """Zeros for the kept layers' halves [K, B, S, P, C] made from `dep`; 16-bit ones as
    bits (`bits.Bits16`: the heads slice them in a loop without a copy of the whole)."""
    if jnp.dtype(dtype).itemsize == 2:
        return Bits16.zeros_from(shape, dtype, dep)
    return zeros_from(shape, dtype, dep)


def stored(buf) -> jax.Array:
    """The array holding a kept buffer's values (a `Bits16` buffer's bits, not its shadow,
    which a forward without derivatives never makes): what to order later work after."""
    return buf.bits if isinstance(buf, Bits16) else buf


def write_slot(buf, x: jax.Array, k: jax.Array, dtype):
    """buf with slot k set to x in the compute dtype (in place). (lax's dynamic update,
    not .at[k].set: the latter is a scatter that XLA lowers with a bounds check, out of
    place: a copy of the kept buffer per step.)"""
    if isinstance(buf, Bits16):
        return buf.update_index(x, k)
    return jax.lax.dynamic_update_index_in_dim(buf, x.astype(dtype), k, 0)
