"""Binary little-endian PLY point clouds: `x y z` float32, `red green blue` uint8 and
optional extra per-vertex properties (rvggt writes `confidence` float32 and `frame`
int32, which point viewers such as CloudCompare show as scalar fields and others skip).
"""

from __future__ import annotations

import os
from typing import Mapping

import numpy as np

__all__ = ["colors_u8", "read_ply_properties", "write_ply"]

PathLike = str | os.PathLike

_BASE = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
# PLY type names <-> numpy (little-endian) dtypes
_PLY_TYPES = {"float": "<f4", "double": "<f8", "uchar": "u1", "char": "i1", "ushort": "<u2", "short": "<i2",
              "uint": "<u4", "int": "<i4", "float32": "<f4", "float64": "<f8", "uint8": "u1", "int8": "i1",
              "uint16": "<u2", "int16": "<i2", "uint32": "<u4", "int32": "<i4"}
_NAMES = {"<f4": "float", "<f8": "double", "|u1": "uchar", "|i1": "char", "<u2": "ushort", "<i2": "short",
          "<u4": "uint", "<i4": "int"}


def colors_u8(colors: np.ndarray | None, n: int) -> np.ndarray:
    """Colours [N, 3] uint8, or float in [0, 1] (scaled), or None (grey) -> [N, 3] uint8."""
    if colors is None:
        return np.full((n, 3), 200, np.uint8)
    colors = np.asarray(colors)
    if colors.shape != (n, 3):
        raise ValueError(f"colors must be [N, 3] with N = {n}; got {colors.shape}")
    if colors.dtype == np.uint8:
        return colors
    return (np.clip(colors.astype(np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_ply(path: PathLike, points: np.ndarray, colors: np.ndarray | None = None,
              extra: Mapping[str, np.ndarray] | None = None) -> None:
    """Binary little-endian PLY point cloud: points [N, 3] (float32 on disk), colors
    [N, 3] uint8 or float in [0, 1] (None: grey), `extra` {name: [N] array} written as
    further vertex properties in their own dtype (float32, int32, uint8, ...)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [N, 3]; got {points.shape}")
    n = points.shape[0]
    extra = {k: np.asarray(v) for k, v in (extra or {}).items()}
    fields = list(_BASE)
    for k, v in extra.items():
        if v.shape != (n,):
            raise ValueError(f"extra property {k!r} must be [N] with N = {n}; got {v.shape}")
        dt = v.dtype.newbyteorder("<") if v.dtype.byteorder not in ("|", "<") else v.dtype
        if dt.str not in _NAMES:
            raise ValueError(f"extra property {k!r}: unsupported dtype {v.dtype}")
        fields.append((k, dt.str))
    rec = np.empty(n, dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = (points[:, i].astype(np.float32) for i in range(3))
    c = colors_u8(colors, n)
    rec["red"], rec["green"], rec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    for k, v in extra.items():
        rec[k] = v
    props = "".join(f"property {_NAMES[np.dtype(t).str]} {name}\n" for name, t in fields)
    header = ("ply\nformat binary_little_endian 1.0\ncomment written by rvggt-jax\n"
              f"element vertex {n}\n{props}end_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())


def read_ply_properties(path: PathLike) -> dict[str, np.ndarray]:
    """Every vertex property of a binary little-endian PLY with one vertex element
    (as `write_ply` writes) -> {name: [N] array}."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary_little_endian PLY is supported")
    n, props, elements = None, [], 0
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            elements += 1
            if parts[1] == "vertex":
                n = int(parts[2])
        elif parts and parts[0] == "property":
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unsupported PLY property {line!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if n is None or elements != 1:
        raise ValueError(f"{path}: expected one vertex element")
    dtype = np.dtype(props)
    body = data[end + len(b"end_header\n"):]
    if len(body) != n * dtype.itemsize:
        raise ValueError(f"{path}: {len(body)} bytes of vertex data for {n} vertices")
    rec = np.frombuffer(body, dtype=dtype, count=n)
    return {name: rec[name].copy() for name, _ in props}
