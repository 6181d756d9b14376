"""The aggregator layers the heads read (`KeptLayer`), and the stacked buffers that hold
them while the aggregator runs: every layer writes its frame and global halves to a slot
(`kept_slots`), so the layer loop's body is the same unconditional in-place write for
every layer.

A layer whose readers take less than its width (each DPT head first normalises a layer's
patch tokens and projects them to 256-1024 of VGGT-1B's 2048 channels) is kept as what
they make of it: `project_layer` runs their first step as soon as the layer exists and
`ProjectedLayer` holds the result, so the layer itself never outlives the next one.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.bits import HalfBuffer, read_buffer, rounded, write_buffer
from rvggt_jax.ops.ordering import materialize, ordered_after, zeros_after


@jax.tree_util.register_pytree_node_class
class KeptLayer:
    """The tokens of one kept aggregator layer, [B, S, P, 2C] float32 on demand, without a
    copy: what the heads take. Its frame-block and global-block halves stay where the
    aggregator left them and are sliced and concatenated per group of frames where a head
    reads them (`frames`, `token`; `array` is the whole layer, a copy).

    Each half is a slot of a stacked [K, B, S, P, C] buffer (compute dtype; 16-bit ones as
    `bits.HalfBuffer`): the frame half in slot `slot`, the global half in `global_slot`
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

    def _halves(self, op, *index) -> list[jax.Array]:
        """op(buffer, slot, *index) on both halves, as stored (the compute dtype; the
        stream's half float32)."""
        return [read_buffer(self.frame_buf, lambda b, *i: op(b, self.slot, *i), *index),
                read_buffer(self.global_buf, lambda b, *i: op(b, self.global_slot, *i), *index)]

    def joined(self, halves: list[jax.Array]) -> jax.Array:
        """The two halves (`_halves`) concatenated along channels, float32."""
        if self.dtype is not None:  # (the residual stream, as its slot would hold it)
            halves = [halves[0].astype(jnp.float32), rounded(halves[1], self.dtype)]
        # (the barrier keeps the float32 cast on the slices)
        return jnp.concatenate(materialize(halves), axis=-1).astype(jnp.float32)

    def _read(self, op, *index) -> jax.Array:
        """op(buffer, slot, *index) on both halves, concatenated along channels, float32."""
        return self.joined(self._halves(op, *index))

    def frames(self, start: jax.Array | int, count: int) -> jax.Array:
        """Frames [start, start + count) of the flattened B*S frames: [count, P, 2C] float32."""
        return self._read(_frames_of_slot(count), start)

    def frame_halves(self, start: jax.Array | int, count: int) -> list[jax.Array]:
        """`frames` before `joined`: the two halves [count, P, C] as stored."""
        return self._halves(_frames_of_slot(count), start)

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


class Part(NamedTuple):
    """A reader's columns [first, first + width) of a `ProjectedLayer`: its level map on the
    token grid (`hw` None), or the level reassembled (`dpt.reassemble`) on an h x w grid."""

    first: int
    width: int
    hw: tuple[int, int] | None = None


class Projection(NamedTuple):
    """What a layer's readers make of it first: `fn(tokens [N, P, 2C] float32) -> [N, Q, F]`
    (Q: positions, F: every reader's columns side by side) and `columns` ((reader, `Part`),
    ...). `remat`: how a group of frames runs in a training step (`dpt.map_frame_groups`),
    or None. `tokens`: tokens another reader takes (the camera's, 0), kept [B, S, 2C] too."""

    fn: Callable[[jax.Array], jax.Array]
    columns: tuple[tuple[str, Part], ...]
    remat: Callable | None = None
    tokens: tuple[int, ...] = ()

    @property
    def width(self) -> int:
        return sum(part.width for _, part in self.columns)


# Bytes of the float32 tokens [G, P, 2C] `project_layer` reads per group of frames.
PROJECT_GROUP_BYTES = 64 * 2**20


@jax.tree_util.register_pytree_node_class
class ProjectedLayer:
    """A kept layer as its readers' first step made it (`project_layer`): `buf`
    [B*S, Q, F] in the compute dtype (16-bit ones as `HalfBuffer`), `columns` as in
    `Projection`, `batch` = (B, S). `raw` is the layer itself when something else reads it
    too (returned layers), else None; `tokens` the {index: [B, S, 2C]} `Projection.tokens` asks."""

    def __init__(self, buf, columns: tuple, batch: tuple[int, int], raw: "KeptLayer | None" = None,
                 tokens: dict | None = None):
        self.buf, self.columns, self.batch, self.raw, self.tokens = buf, columns, batch, raw, dict(tokens or {})

    @property
    def shape(self) -> tuple[int, ...]:
        return self.batch + tuple(self.buf.shape[1:])

    @property
    def ndim(self) -> int:
        return 4

    def part(self, reader: str) -> Part:
        """`reader`'s columns (first, width, and the grid of a reassembled map)."""
        for name, part in self.columns:
            if name == reader:
                return part
        raise KeyError(f"this layer was projected for {[c[0] for c in self.columns]}, not for {reader!r}")

    def frames(self, start: jax.Array | int, count: int) -> jax.Array:
        """Frames [start, start + count) of the flattened B*S frames: [count, Q, F] float32."""
        return read_buffer(self.buf, lambda b, s: jax.lax.dynamic_slice_in_dim(b, s, count, 0), start
                           ).astype(jnp.float32)

    def token(self, index: int) -> jax.Array:
        if index in self.tokens:
            return self.tokens[index]
        return self._raw().token(index)

    def array(self) -> jax.Array:
        return self._raw().array()

    def _raw(self) -> "KeptLayer":
        if self.raw is None:
            raise ValueError("this layer was kept only as its heads' projections; ask for it with "
                             "config.with_outputs(layers=...) to keep its tokens")
        return self.raw

    def tree_flatten(self):
        return (self.buf, self.raw, self.tokens), (self.columns, self.batch)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(children[0], aux[0], aux[1], children[1], children[2])


def project_layer(layer: KeptLayer, projection: Projection, dtype, clear: bool = True
                  ) -> tuple[jax.Array, KeptLayer]:
    """The readers' first step on every frame of `layer` [B, S, P, 2C] -> ([B*S, Q, F] in
    `dtype` (16-bit: a `HalfBuffer` buffer), the layer's buffers after it), computed for
    groups of frames whose float32 tokens take PROJECT_GROUP_BYTES (the layer's float32
    copy never exists). When the group does not divide B*S, the last group starts before
    the end and recomputes a few frames (the first step is per frame: the same values).

    The loop zeroes the first frame of each group in the layer's slots once read (no
    later group reads it; the next layers overwrite the slots): a loop that only reads a
    buffer passes it through, XLA drops the pass-through, and a later in-place update of
    the buffer then needs a copy (XLA:CPU copied the kept frame halves and the stream:
    +4 GB in dense's plan at 1000 frames of VGGT-1B). The next layers update the returned
    buffers. A global half read from the stream (`layer.dtype` set) is left as it is, and
    so is all of a layer kept whole too (`clear` False: its slots are its own)."""
    b, s, p, c2 = layer.shape
    n = b * s
    g = int(min(n, max(1, PROJECT_GROUP_BYTES // (p * c2 * 4))))
    groups = -(-n // g)
    spec = jax.eval_shape(projection.fn, jax.ShapeDtypeStruct((g, p, c2), jnp.float32))
    if spec.shape[0] != g or spec.shape[-1] != projection.width:
        raise ValueError(f"a projection of {g} frames gave {spec.shape}; expected [{g}, Q, {projection.width}]")
    buf = kept_buffer((n,) + spec.shape[1:], dtype, layer.frames(0, 1))

    def group(halves):
        return projection.fn(layer.joined(halves))

    if projection.remat is not None:
        # (a checkpoint keeps the group's halves as stored, a copy of the layer in all: the
        # buffers it reads are overwritten by the next layers, so keeping them would keep
        # a copy of each whole buffer)
        group = projection.remat(group)

    def rebuilt(frame_buf, global_buf) -> KeptLayer:
        return KeptLayer(frame_buf, global_buf, layer.slot, layer.global_slot, layer.dtype)

    def body(i, carry):
        buf, frame_buf, global_buf = carry
        start = jnp.minimum(i * g, n - g)
        y = group(rebuilt(frame_buf, global_buf).frame_halves(start, g))
        buf = write_buffer(buf, _set_rows, y, start)
        if clear:
            frame_buf = _zero_frame(frame_buf, layer.slot, start)
        if clear and layer.dtype is None:
            global_buf = _zero_frame(global_buf, layer.global_slot, start)
        return buf, frame_buf, global_buf

    buf, frame_buf, global_buf = jax.lax.fori_loop(0, groups, body, (buf, layer.frame_buf, layer.global_buf))
    return buf, rebuilt(frame_buf, global_buf)


def _set_frame(buf: jax.Array, x: jax.Array, index) -> jax.Array:
    """buf [K, B, S, P, C] with frame `start` (of the flattened B*S) of slot `slot` set to
    x [P, C]; index = (slot, start)."""
    slot, start = index
    flat = buf.reshape((buf.shape[0], -1) + buf.shape[3:])
    zero = jnp.zeros((), jnp.int32)
    return jax.lax.dynamic_update_slice(flat, x[None, None], (slot, start, zero, zero)).reshape(buf.shape)


def _zero_frame(buf, slot, start):
    """`_set_frame` with zeros, on a plain or a `HalfBuffer` buffer."""
    index = (jnp.asarray(slot, jnp.int32), jnp.asarray(start, jnp.int32))
    return write_buffer(buf, _set_frame, jnp.zeros(buf.shape[3:], buf.dtype), index)


def _set_rows(buf: jax.Array, x: jax.Array, start) -> jax.Array:
    return jax.lax.dynamic_update_slice_in_dim(buf, x, start, 0)


def _set_slot(buf: jax.Array, x: jax.Array, k) -> jax.Array:
    return jax.lax.dynamic_update_index_in_dim(buf, x, k, 0)


def _frames_of_slot(count: int):
    """op(buf [K, B, S, P, C], slot, start) -> frames [start, start + count) of the
    flattened B*S frames of slot `slot`, [count, P, C]."""
    def part(buf, slot, start):
        # (buf: float32, or a 16-bit buffer's bits; plain slices, which also carry
        # the derivatives of `bits.HalfBuffer`)
        flat = buf.reshape((buf.shape[0], -1) + buf.shape[3:])  # [K, B*S, P, C]
        # Frames first, then the slot, both dynamic slices (a static slot slice is
        # loop-invariant: XLA would hoist it, cast to float32, out of the heads' loop)
        frames = jax.lax.dynamic_slice_in_dim(flat, start, count, 1)
        return jax.lax.dynamic_index_in_dim(frames, slot, 0, keepdims=False)

    return part


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
    bits (`bits.HalfBuffer`: the heads slice them in a loop without a copy of the whole)."""
    if jnp.dtype(dtype).itemsize == 2:
        return HalfBuffer.zeros_after(shape, dtype, dep)
    return zeros_after(shape, dtype, dep)


def stored(buf) -> jax.Array:
    """The array holding a kept buffer's values (a `HalfBuffer` buffer's bits, not its shadow,
    which a forward without derivatives never makes): what to order later work after."""
    return buf.bits if isinstance(buf, HalfBuffer) else buf


def write_slot(buf, x: jax.Array, k: jax.Array, dtype):
    """buf with slot k set to x in the compute dtype (in place). (lax's dynamic update,
    not .at[k].set: the latter is a scatter that XLA lowers with a bounds check, out of
    place: a copy of the kept buffer per step.)"""
    return write_buffer(buf, _set_slot, x.astype(dtype), k)


# ---------------------------------------------------------------------------------------
# The kept layers while the aggregator runs: every buffer decision in one place
# ---------------------------------------------------------------------------------------


@jax.tree_util.register_pytree_node_class
class KeptLayers:
    """The buffers the aggregator writes the heads' layers to, and every decision about
    them: slots, global halves, where the layer loop is cut, what is ordered after what.

    - `frame`, `global_`: [K, B, S, P, C] in the compute dtype (16-bit: `HalfBuffer`);
      kept layer j owns slot j, any other layer writes the next kept layer's slot
      (`kept_slots`), so the loop body is one unconditional write.
    - A kept last layer's global half is the final stream itself: the global buffer has
      one slot less, and the layers after `writes_global` write no global half.
    - A projected layer ends its scan: `project` reads its slots before the next layer
      overwrites them. (Static facts are the pytree's aux data.)"""

    def __init__(self, frame, global_, keep: tuple[int, ...], slots: tuple[int, ...], writes_global: int,
                 projects: tuple[int, ...], dtype: str):
        self.frame, self.global_ = frame, global_
        self.keep, self.slots, self.writes_global = keep, slots, writes_global
        self.projects, self.dtype = projects, dtype

    @classmethod
    def start(cls, depth: int, keep, projects, shape: tuple[int, int, int, int], dtype, dep: jax.Array
              ) -> "KeptLayers":
        """The empty buffers for `depth` layers of tokens `shape` = (B, S, P, C), keeping
        `keep` whole and projecting `projects` (no slot of their own unless kept); made
        after `dep` (after the patch embed: docs/memory_layout.md)."""
        keep = tuple(sorted(set(keep)))
        slot, spare = kept_slots(depth, keep)
        last_is_x = bool(keep) and keep[-1] == depth - 1
        writes_global = (keep[-2] if len(keep) > 1 else -1) if last_is_x else depth - 1  # up to this layer
        n_global = len(keep) + spare - int(last_is_x)
        if not keep:  # (every layer read is projected: no halves to keep)
            writes_global, n_global = -1, 0
        full = (len(keep) + spare,) + tuple(shape)
        frame = kept_buffer(full, dtype, dep)
        global_ = kept_buffer((n_global,) + full[1:], dtype, jax.tree.leaves(frame)[0]) if n_global else None
        return cls(frame, global_, keep, tuple(int(k) for k in slot), writes_global, tuple(sorted(projects)),
                   jnp.dtype(dtype).name)

    def scans(self, runs) -> list[tuple[int, ...]]:
        """The runs of layers that share a compiled body, cut where the global halves stop
        and after each projected layer: one `lax.scan` each."""
        w = self.writes_global
        groups = [g for run in runs for g in (tuple(i for i in run if i <= w), tuple(i for i in run if i > w)) if g]
        out = []
        for run in groups:
            part = []
            for i in run:
                part.append(i)
                if i in self.projects:
                    out.append(tuple(part))
                    part = []
            if part:
                out.append(tuple(part))
        return out

    def slots_of(self, group) -> jax.Array:  # [len(group)] int32: the scan's input
        return jnp.asarray([self.slots[i] for i in group], jnp.int32)

    def stores_global(self, group) -> bool:  # (a scan is on one side of writes_global)
        return group[0] <= self.writes_global

    def after_frame_block(self, x: jax.Array, k: jax.Array) -> "KeptLayers":
        """The frame block's output x [B, S, P, C] written to slot k."""
        return self._with(frame=write_slot(self.frame, x, k, self.dtype))

    def before_global_block(self, x: jax.Array, p_global, single: bool):
        """(x, self, p_global) ordered so that the global block, which updates x in place,
        runs after the frame half's write has read x (else the stream is copied for the
        write: docs/memory_layout.md). The order comes through the block's weights, which
        leaves the stream a single buffer; a run of one layer (`single`: no loop, its slot
        a constant) settles x and the write first."""
        kept = self
        if single:
            x, frame = materialize((x, self.frame))
            kept = self._with(frame=frame)
        p_global = jax.tree.map(lambda w: ordered_after(w, stored(kept.frame)), p_global)
        return x, kept, p_global

    def after_global_block(self, x: jax.Array, k: jax.Array, store: bool) -> "KeptLayers":
        """The global block's output x [B, S, P, C] written to slot k when `store`."""
        return self._with(global_=write_slot(self.global_, x, k, self.dtype)) if store else self

    def project(self, i: int, x: jax.Array, projection: Projection, shape) -> tuple["KeptLayers", "ProjectedLayer",
                                                                                   jax.Array | None]:
        """Layer i's projection, as its slots hold it at the end of its scan (the next layer
        overwrites them), with x the stream [B, S*P, C] and `shape` = (B, S, P, C) ->
        (self after it, the `ProjectedLayer` (its `raw` unset), the value the next scan
        must start after, or None). A layer past `writes_global` reads its global half
        from the stream, which the loop only reads."""
        b, s, p, c = shape
        k = self.slots[i]
        if i <= self.writes_global:
            layer = KeptLayer(self.frame, self.global_, k)
        else:
            layer = KeptLayer(self.frame, x.reshape(1, b, s, p, c), k, 0, self.dtype)
        tokens = {t: layer.token(t) for t in projection.tokens}  # (before the loop clears the slots)
        buf, layer = project_layer(layer, projection, self.dtype, clear=i not in self.keep)
        kept = self._with(frame=layer.frame_buf, global_=layer.global_buf if i <= self.writes_global else self.global_)
        # a buffer the loop only reads: the next scan starts after it (through one weight:
        # a dependency of the stream, x + 0, gets a buffer of its own)
        after = stored(buf) if (i in self.keep or i > self.writes_global) else None
        return kept, ProjectedLayer(buf, projection.columns, (b, s), tokens=tokens), after

    def outputs(self, x: jax.Array, shape) -> dict[int, KeptLayer]:
        """{layer: `KeptLayer`} of the kept layers once the loop is done, x the final
        stream [B, S*P, C]; `shape` = (B, S, P, C)."""
        out = {i: KeptLayer(self.frame, self.global_, j) for j, i in enumerate(self.keep)}
        if self.keep and self.keep[-1] > self.writes_global:  # (the last layer: the stream)
            out[self.keep[-1]] = KeptLayer(self.frame, x.reshape((1,) + tuple(shape)), len(self.keep) - 1, 0,
                                           self.dtype)
        return out

    def _with(self, **buffers) -> "KeptLayers":
        kept = KeptLayers(self.frame, self.global_, self.keep, self.slots, self.writes_global, self.projects,
                          self.dtype)
        for name, value in buffers.items():
            setattr(kept, name, value)
        return kept

    def tree_flatten(self):
        return (self.frame, self.global_), (self.keep, self.slots, self.writes_global, self.projects, self.dtype)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children, *aux)


def weights_after(p, dep: jax.Array | None):
    """Aggregator weights `p` with the frame blocks' smallest weight computed after `dep`
    (None: unchanged): the next scan, which takes it, starts after `dep` exists."""
    if dep is None:
        return p
    frame = p["frame_blocks"]
    leaves, tree = jax.tree.flatten(frame)
    small = min(range(len(leaves)), key=lambda k: leaves[k].size)
    leaves[small] = ordered_after(leaves[small], dep)
    return {**p, "frame_blocks": jax.tree.unflatten(tree, leaves)}
