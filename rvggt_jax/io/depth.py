"""16-bit PNG depth maps: `depth = value * scale` with one `scale` for all frames (in
`depth_scale.json`), 0 where there is no depth; plus coloured previews (near = bright)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from rvggt_jax.io.plots import colorize

__all__ = ["write_depth_frames", "write_depth_pngs", "write_depth_scale"]

PathLike = str | os.PathLike


def write_depth_pngs(folder: PathLike, stems: Sequence[str], depth: np.ndarray, valid: np.ndarray | None = None,
                     preview_folder: PathLike | None = None) -> float:
    """16-bit depth PNGs `folder/<stem>.png` and `folder/depth_scale.json`; colour
    previews `preview_folder/<stem>.png` (if given).

    depth [S, H, W] (or [S, H, W, 1]); valid [S, H, W] bool (default: finite and > 0).
    One scale for every frame: `depth = png_value * scale`, with the largest valid depth
    at 65535; 0 marks pixels without depth. Returns the scale.
    """
    d, ok = _depth_and_valid(depth, valid, len(stems))
    dmax = float(d[ok].max()) if ok.any() else 1.0
    scale = dmax / 65535.0
    write_depth_frames(folder, stems, d, ok, scale, preview_folder)
    write_depth_scale(folder, scale, dmax, stems)
    return scale


def _depth_and_valid(depth, valid, frames: int) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim == 4 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 3 or d.shape[0] != frames:
        raise ValueError(f"depth must be [S, H, W] with S = {frames}; got {np.shape(depth)}")
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    return d, ok


def write_depth_frames(folder: PathLike, stems: Sequence[str], depth: np.ndarray, valid: np.ndarray | None,
                       scale: float, preview_folder: PathLike | None = None) -> None:
    """The PNGs of `write_depth_pngs` for some frames, at a given `scale` (a long run
    writes them chunk by chunk, with the scale of the whole sequence); depth beyond
    65535 x scale is clipped there."""
    d, ok = _depth_and_valid(depth, valid, len(stems))
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, stem in enumerate(stems):
        q = np.where(ok[i], np.clip(np.round(d[i] / scale), 1, 65535), 0).astype(np.uint16)
        Image.fromarray(q).save(folder / f"{stem}.png")
    if preview_folder is not None:
        pf = Path(preview_folder)
        pf.mkdir(parents=True, exist_ok=True)
        for i, stem in enumerate(stems):
            vals = d[i][ok[i]]
            lo, hi = (np.percentile(vals, [2, 98]) if vals.size else (0.0, 1.0))
            # near = bright: colour inverse depth ranks
            img = colorize(-d[i], -hi, -lo, invalid=~ok[i])
            Image.fromarray(img).save(pf / f"{stem}.png")


def write_depth_scale(folder: PathLike, scale: float, max_depth: float, stems: Sequence[str]) -> None:
    """`folder/depth_scale.json`: how the PNGs' values map to depth."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "depth_scale.json", "w") as f:
        json.dump(dict(scale=scale, formula="depth = png_value * scale (16-bit PNG); 0 = no depth",
                       units="the model's depth units (scene scale normalised by the model, not metres)",
                       max_depth=max_depth, frames=list(stems)), f, indent=1)
        f.write("\n")
