"""Readers of the files rvggt writes, for the tests only (the package writes these
formats; `rvggt view` reads the PLY through `rvggt_jax.io.ply.read_ply_properties`)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from rvggt_jax.io.ply import read_ply_properties

PathLike = str | os.PathLike

_XYZ_RGB = ("x", "y", "z", "red", "green", "blue")


def read_ply(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] float32 and colors [N, 3] uint8 of a PLY written by `write_ply`
    (extra properties are ignored; `read_ply_properties` returns them)."""
    p = read_ply_properties(path)
    missing = [k for k in _XYZ_RGB if k not in p]
    if missing:
        raise ValueError(f"{path}: unexpected PLY layout, no {missing}")
    pts = np.stack([p["x"], p["y"], p["z"]], axis=1).astype(np.float32)
    cols = np.stack([p["red"], p["green"], p["blue"]], axis=1).astype(np.uint8)
    return pts, cols


def read_colmap_text(folder: PathLike) -> dict[str, Any]:
    """Parse a COLMAP text model (the subset `write_colmap_text` writes, following
    COLMAP's own reader: '#' comments, two lines per image) -> {"cameras": {id: {model,
    width, height, params}}, "images": {id: {qvec, tvec, camera_id, name, points2d}},
    "points": {id: {xyz, rgb, error, track}}}."""
    folder = Path(folder)
    cameras = {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        it = line.split(" ")
        cameras[int(it[0])] = dict(model=it[1], width=int(it[2]), height=int(it[3]),
                                   params=np.array([float(v) for v in it[4:]]))
    images = {}
    lines = (folder / "images.txt").read_text().split("\n")
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        it = line.split(" ")
        if len(it) != 10:
            raise ValueError(f"images.txt: bad image line {line!r}")
        if i >= len(lines):
            raise ValueError("images.txt: missing POINTS2D line")
        pts2d = lines[i].split()
        i += 1
        images[int(it[0])] = dict(qvec=np.array([float(v) for v in it[1:5]]), tvec=np.array([float(v) for v in it[5:8]]),
                                  camera_id=int(it[8]), name=it[9], points2d=pts2d)
    points = {}
    for line in (folder / "points3D.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        it = line.split()
        points[int(it[0])] = dict(xyz=np.array([float(v) for v in it[1:4]]), rgb=np.array([int(v) for v in it[4:7]]),
                                  error=float(it[7]), track=[int(v) for v in it[8:]])
    return dict(cameras=cameras, images=images, points=points)


def read_depth_png(path: PathLike, scale: float | None = None) -> np.ndarray:
    """Depth [H, W] float32 from a `write_depth_pngs` file; `scale` defaults to the one
    in the `depth_scale.json` beside it. 0 = no depth."""
    path = Path(path)
    if scale is None:
        scale = json.loads((path.parent / "depth_scale.json").read_text())["scale"]
    with Image.open(path) as im:
        v = np.asarray(im).astype(np.float64)
    return (v * scale).astype(np.float32)
