"""Read the vertices of any PLY file (ASCII or binary, with or without faces): the
ground-truth clouds of DTU (`Points/stl/stlNNN_total.ply`) and ScanNet
(`<scene>_vh_clean_2.ply`, a mesh whose vertices are the cloud)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.errors import DatasetError

__all__ = ["read_ply_points"]

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply_points(path: str | Path) -> np.ndarray:
    """x, y, z of the `vertex` element of a PLY file -> [N, 3] float64.

    The vertex element must come first (as in every common writer); list properties
    (faces) after it are not read."""
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise DatasetError(f"not a PLY file: {path}")
        fmt, n, props, elements = None, None, [], []
        while True:
            line = f.readline()
            if not line:
                raise DatasetError(f"PLY header without end_header: {path}")
            parts = line.decode("ascii", "replace").split()
            if not parts:
                continue
            if parts[0] == "format":
                fmt = parts[1]
            elif parts[0] == "element":
                elements.append(parts[1])
                if parts[1] == "vertex":
                    n = int(parts[2])
            elif parts[0] == "property" and elements[-1:] == ["vertex"]:
                if parts[1] == "list" or parts[1] not in _TYPES:
                    raise DatasetError(f"unsupported PLY vertex property {' '.join(parts[1:])!r}: {path}")
                props.append((parts[2], _TYPES[parts[1]]))
            elif parts[0] == "end_header":
                break
        if elements[:1] != ["vertex"] or n is None or not {"x", "y", "z"} <= {p for p, _ in props}:
            raise DatasetError(f"PLY file has no vertex x, y, z (as its first element): {path}")
        if fmt == "ascii":
            rows = [f.readline().split() for _ in range(n)]
            names = [p for p, _ in props]
            try:
                arr = np.array([[float(r[names.index(c)]) for c in "xyz"] for r in rows])
            except (IndexError, ValueError):
                raise DatasetError(f"malformed ASCII PLY vertex data: {path}") from None
            return arr.reshape(-1, 3)
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            raise DatasetError(f"unknown PLY format {fmt!r}: {path}")
        end = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(p, end + t) for p, t in props])
        data = f.read(n * dtype.itemsize)
        if len(data) < n * dtype.itemsize:
            raise DatasetError(f"PLY file is truncated ({n} vertices announced): {path}")
        rec = np.frombuffer(data, dtype=dtype, count=n)
        return np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
