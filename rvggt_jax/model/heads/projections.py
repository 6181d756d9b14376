"""Which kept layers the DPT heads read as their first step, and that step
(`kept.Projection`): the aggregator keeps such a layer as a `kept.ProjectedLayer`.

Each DPT head (depth, points, the track head's extractor) first normalises a layer's
patch tokens and projects them to its level's width (`dpt.level_map`): VGGT-1B's depth
and point heads read 256 + 256 of layer 4's 2048 channels and 512 + 512 of layer 11's.
Design and measurements: docs/memory_layout.md ("Layers kept as the heads' first step").
"""

from __future__ import annotations

from typing import Callable, Iterable, Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from rvggt_jax.config import TokenGrid
from rvggt_jax.model.heads.dpt import READERS, level_map
from rvggt_jax.model.kept import Projection
from rvggt_jax.model.params import Params


def head_projections(readers: Mapping[str, tuple[Params, Sequence[int]]], grid: TokenGrid, token_width: int,
                     raw: Iterable[int] = (), remat: Callable | None = None) -> dict[int, Projection]:
    """The layers to keep as their DPT heads' first step (`kept.Projection`): readers
    {name: (DPT params, the 4 layers it reads)} (the track head's extractor included);
    a layer is projected when its readers' projections together are narrower than its
    tokens (token_width = 2C: VGGT-1B's layer 4 holds 2048 channels, its depth and point
    heads read 256 + 256 of them) and nothing in `raw` reads its tokens (the camera
    head, a returned layer). Every op of the first step is per token, so its values are
    the ones the head would make (the same float32 ops; in a 16-bit compute dtype they
    are stored rounded to it, as the tokens were). `remat`: see `map_frame_groups`."""
    raw = set(raw)
    by_layer: dict[int, list[tuple[str, Params, int]]] = {}
    for name, (params, layer_idx) in readers.items():
        if name not in READERS:
            raise ValueError(f"unknown DPT reader {name!r}; expected one of {READERS}")
        if len(layer_idx) != 4:
            raise ValueError(f"the DPT head reads exactly 4 layers, got {tuple(layer_idx)}")
        for level, layer in enumerate(layer_idx):
            by_layer.setdefault(layer, []).append((name, params, level))
    grid_hw = grid.hw
    out = {}
    for layer, entries in sorted(by_layer.items()):
        widths = [params["projects"][str(level)]["kernel"].shape[-1] for _, params, level in entries]
        if layer in raw or sum(widths) >= token_width or len({e[0] for e in entries}) < len(entries):
            continue
        starts = np.cumsum([0] + widths[:-1])
        columns = tuple((name, int(a), int(w)) for (name, _, _), a, w in zip(entries, starts, widths))

        def fn(tokens, entries=entries):
            n = tokens.shape[0]
            maps = [level_map(params, level, tokens, grid.patch_start_idx, grid_hw) for _, params, level in entries]
            return jnp.concatenate([m.reshape(n, grid_hw[0] * grid_hw[1], -1) for m in maps], axis=-1)

        out[layer] = Projection(fn, columns, remat)
    return out
