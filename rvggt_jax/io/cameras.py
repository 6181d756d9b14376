"""`cameras.json`: one entry per image, `{"image", "extrinsic" (3x4 world-to-camera,
OpenCV axes: x right, y down, z forward), "intrinsic" (3x3 pinhole in pixels, continuous
coordinates: the image spans [0, W] x [0, H]), "width", "height"}`, matrices one row per
line."""

from __future__ import annotations

import json
import os
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["check_cameras", "write_cameras_json"]

PathLike = str | os.PathLike


def check_cameras(names: Sequence[str], extrinsics, intrinsics, sizes) -> tuple[np.ndarray, np.ndarray]:
    """extrinsics [S, 3, 4], intrinsics [S, 3, 3] as float64 for S names and S sizes;
    ValueError naming the shapes otherwise."""
    e = np.asarray(extrinsics, dtype=np.float64)
    k = np.asarray(intrinsics, dtype=np.float64)
    s = len(names)
    if e.shape != (s, 3, 4) or k.shape != (s, 3, 3) or len(sizes) != s:
        raise ValueError(f"{s} names need extrinsics [S,3,4], intrinsics [S,3,3], S sizes; "
                         f"got {e.shape}, {k.shape}, {len(sizes)}")
    return e, k


def write_cameras_json(path: PathLike, names: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                       sizes: Sequence[tuple[int, int]], extra: Sequence[Mapping[str, Any]] | None = None,
                       meta: Mapping[str, Any] | None = None) -> None:
    """`{"frames": [{"image", "extrinsic" (3x4 world-to-camera, OpenCV), "intrinsic"
    (3x3), "width", "height"} + extra[i]], **meta}` as JSON."""
    e, k = check_cameras(names, extrinsics, intrinsics, sizes)
    frames = []
    for i, name in enumerate(names):
        fr = dict(image=name, extrinsic=e[i].tolist(), intrinsic=k[i].tolist(),
                  width=int(sizes[i][0]), height=int(sizes[i][1]))
        if extra is not None:
            fr.update(extra[i])
        frames.append(fr)
    doc = dict(meta or {})
    doc["frames"] = frames
    text = _json_rows(doc)
    with open(path, "w") as f:
        f.write(text + "\n")


def _json_rows(obj: Any, indent: str = "") -> str:
    """JSON with lists of numbers on one line (one matrix row per line)."""
    inner = indent + " "
    if isinstance(obj, Mapping):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_json_rows(v, inner)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(obj, (list, tuple)):
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in obj):
            return json.dumps(list(obj))
        return "[\n" + ",\n".join(inner + _json_rows(v, inner) for v in obj) + "\n" + indent + "]"
    return json.dumps(obj)
