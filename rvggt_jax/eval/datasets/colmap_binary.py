"""COLMAP sparse models: cameras and images of `cameras.bin` / `images.bin` or the
`.txt` versions (the format of COLMAP's documentation, "Output format").
Points (`points3D.*`) are not needed by the evaluation and are not read."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError
from rvggt_jax.io.colmap import colmap_qvec, colmap_rotation

__all__ = ["read_model", "write_model_bin"]

# model id -> (name, number of parameters)
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
          4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
          8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}
_BY_NAME = {name: (mid, n) for mid, (name, n) in MODELS.items()}


def pinhole(model: str, params) -> np.ndarray:
    """[3, 3] pinhole part of a COLMAP camera (distortion ignored)."""
    p = list(params)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
        f, cx, cy = p[:3]
        fx = fy = f
    else:
        fx, fy, cx, cy = p[:4]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def _read_bin(folder: Path):
    cams, imgs = {}, {}
    try:
        with open(folder / "cameras.bin", "rb") as f:
            for _ in range(struct.unpack("<Q", f.read(8))[0]):
                cid, mid, w, h = struct.unpack("<iiQQ", f.read(24))
                name, n = MODELS[mid]
                cams[cid] = (name, w, h, struct.unpack(f"<{n}d", f.read(8 * n)))
        with open(folder / "images.bin", "rb") as f:
            for _ in range(struct.unpack("<Q", f.read(8))[0]):
                iid, *qt, cid = struct.unpack("<I7dI", f.read(64))
                name = b""
                while (c := f.read(1)) not in (b"\0", b""):
                    name += c
                npts = struct.unpack("<Q", f.read(8))[0]
                f.seek(24 * npts, 1)
                imgs[iid] = (name.decode("utf-8"), np.array(qt[:4]), np.array(qt[4:]), cid)
    except (struct.error, KeyError) as e:
        raise DatasetError(f"malformed COLMAP binary model in {folder}: {e}") from None
    return cams, imgs


def _read_txt(folder: Path):
    cams, imgs = {}, {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            it = line.split()
            cams[int(it[0])] = (it[1], int(it[2]), int(it[3]), tuple(map(float, it[4:])))
    lines = [ln for ln in (folder / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    for j in range(0, len(lines), 2):
        it = lines[j].split()
        if not it:
            continue
        imgs[int(it[0])] = (" ".join(it[9:]), np.array(it[1:5], float), np.array(it[5:8], float), int(it[8]))
    return cams, imgs


def read_model(folder: Path) -> list[dict]:
    """Images of a model folder (bin preferred over txt), sorted by name: [{"name",
    "extrinsic" [3, 4] world-to-camera, "intrinsic" [3, 3], "width", "height"}]."""
    if (folder / "images.bin").is_file() and (folder / "cameras.bin").is_file():
        cams, imgs = _read_bin(folder)
    elif (folder / "images.txt").is_file() and (folder / "cameras.txt").is_file():
        cams, imgs = _read_txt(folder)
    else:
        raise DatasetError(f"missing COLMAP model (cameras.bin + images.bin, or the .txt pair): {folder}")
    out = []
    for name, q, t, cid in imgs.values():
        if cid not in cams:
            raise DatasetError(f"image {name} refers to camera {cid}, absent from the model in {folder}")
        model, w, h, params = cams[cid]
        out.append(dict(name=name, extrinsic=np.concatenate([colmap_rotation(q), t[:, None]], axis=1),
                        intrinsic=pinhole(model, params), width=w, height=h))
    return sorted(out, key=lambda r: r["name"])


def write_model_bin(folder: Path, names, extrinsics, intrinsics, sizes) -> None:
    """cameras.bin (PINHOLE, one per image) + images.bin (no 2D points) + an empty
    points3D.bin."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(names)))
        for i, (k, (w, h)) in enumerate(zip(intrinsics, sizes)):
            f.write(struct.pack("<iiQQ4d", i + 1, 1, w, h, k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
    with open(folder / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(names)))
        for i, (n, e) in enumerate(zip(names, extrinsics)):
            f.write(struct.pack("<I7dI", i + 1, *colmap_qvec(e[:, :3]), *e[:, 3], i + 1))
            f.write(n.encode("utf-8") + b"\0" + struct.pack("<Q", 0))
    with open(folder / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", 0))
