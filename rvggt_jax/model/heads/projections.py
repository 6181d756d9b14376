"""Which kept layers the DPT heads read as their first steps, and those steps
(`kept.Projection`): the aggregator keeps such a layer as a `kept.ProjectedLayer`.

Each DPT head (depth, points, the track head's extractor) first normalises a layer's
patch tokens and projects them to its level's width (`dpt.level_map`): VGGT-1B's depth
and point heads read 256 + 256 of layer 4's 2048 channels and 512 + 512 of layer 11's.
In the low-memory mode a layer read at a coarse level goes on to the level's whole
reassembly (`dpt.reassemble`: resized, at the fusion width): VGGT-1B's layer 23 is then
256 + 256 channels on a quarter of the positions.
Design and measurements: docs/memory_layout.md ("Layers kept as the heads' first step").
"""

from __future__ import annotations

from typing import Callable, Iterable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.config import TokenGrid
from rvggt_jax.model.heads.dpt import READERS, level_map, reassemble
from rvggt_jax.model.kept import Part, Projection
from rvggt_jax.model.params import Params


def head_projections(readers: Mapping[str, tuple[Params, Sequence[int], bool]], grid: TokenGrid, token_width: int,
                     raw: Iterable[int] = (), remat: Callable | None = None, reassembled: bool = False,
                     tokens: Mapping[int, tuple[int, ...]] | None = None) -> dict[int, Projection]:
    """The layers to keep as their DPT heads' first steps (`kept.Projection`): readers
    {name: (DPT params, the 4 layers it reads, whether it adds the positional map)} (the
    track head's extractor included). A layer is projected when its readers' projections
    together are narrower than its tokens (token_width = 2C: VGGT-1B's layer 4 holds 2048
    channels, its depth and point heads read 256 + 256 of them) and nothing in `raw`
    reads its tokens (a returned layer). Every op of these steps is per position, so its
    values are the ones the head would make (the same float32 ops; in a 16-bit compute
    dtype they are stored rounded to it, as the tokens were). `remat`: see
    `map_frame_groups`.

    reassembled: a layer is kept as its readers' reassembled maps instead whenever those
    take fewer values than the projections (the coarse levels: VGGT-1B's levels 2 and 3;
    the fine ones are upsampled, larger). tokens: {layer: token indices} another reader
    takes from a projected layer (the camera token of the last layer; kept beside it)."""
    raw, tokens = set(raw), dict(tokens or {})
    by_layer: dict[int, list[tuple[str, Params, int, bool]]] = {}
    for name, (params, layer_idx, pos_embed) in readers.items():
        if name not in READERS:
            raise ValueError(f"unknown DPT reader {name!r}; expected one of {READERS}")
        if len(layer_idx) != 4:
            raise ValueError(f"the DPT head reads exactly 4 layers, got {tuple(layer_idx)}")
        for level, layer in enumerate(layer_idx):
            by_layer.setdefault(layer, []).append((name, params, level, pos_embed))
    tokens_in = jax.ShapeDtypeStruct((1, grid.patch_start_idx + grid.hw[0] * grid.hw[1], token_width), jnp.float32)
    out = {}
    for layer, entries in sorted(by_layer.items()):
        if layer in raw or len({e[0] for e in entries}) < len(entries):
            continue
        steps = [_projected(params, level, grid) for _, params, level, _ in entries]
        maps = [f.shape(tokens_in) for f in steps]
        if reassembled:
            whole = [_reassembled(params, level, grid, pos) for _, params, level, pos in entries]
            whole_maps = [f.shape(tokens_in) for f in whole]
            # (side by side needs one grid: the readers of a layer read it at one level)
            if len({m[1:3] for m in whole_maps}) == 1 and _values(whole_maps) < _values(maps):
                steps, maps = whole, whole_maps
        if _values(maps) >= grid.hw[0] * grid.hw[1] * token_width:
            continue
        widths = [m[-1] for m in maps]
        hw = None if steps[0].projected_only else tuple(maps[0][1:3])
        starts = np.cumsum([0] + widths[:-1])
        columns = tuple((name, Part(int(a), int(w), hw)) for (name, _, _, _), a, w in zip(entries, starts, widths))

        def fn(x, steps=steps):
            return jnp.concatenate([_flat(f(x)) for f in steps], axis=-1)

        out[layer] = Projection(fn, columns, remat, tuple(tokens.get(layer, ())))
    return out


class _Step:
    """One reader's first step on a layer's tokens [N, P, 2C] -> a map [N, h, w, F]:
    its level map (`projected_only`), or the whole reassembled level."""

    def __init__(self, params: Params, level: int, grid: TokenGrid, pos_embed: bool, projected_only: bool):
        self.params, self.level, self.grid = params, level, grid
        self.pos_embed, self.projected_only = pos_embed, projected_only

    def apply(self, params: Params, x: jax.Array) -> jax.Array:
        g = self.grid
        m = level_map(params, self.level, x, g.patch_start_idx, g.hw)
        return m if self.projected_only else reassemble(params, self.level, m, g.image_hw, self.pos_embed)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.apply(self.params, x)

    def shape(self, x: jax.ShapeDtypeStruct) -> tuple[int, ...]:
        """The map's shape for tokens `x`: a level map's from its projection's kernel, a
        reassembled one traced (the parameters as arguments: abstract ones too)."""
        if self.projected_only:
            return (x.shape[0], *self.grid.hw, self.params["projects"][str(self.level)]["kernel"].shape[-1])
        return jax.eval_shape(self.apply, self.params, x).shape


def _projected(params: Params, level: int, grid: TokenGrid) -> _Step:
    return _Step(params, level, grid, False, True)


def _reassembled(params: Params, level: int, grid: TokenGrid, pos_embed: bool) -> _Step:
    return _Step(params, level, grid, pos_embed, False)


def _values(maps) -> int:
    """Values per frame of maps of shapes [1, h, w, F]."""
    return int(sum(np.prod(m[1:]) for m in maps))


def _flat(m: jax.Array) -> jax.Array:
    return m.reshape(m.shape[0], m.shape[1] * m.shape[2], m.shape[3])
