"""A generic folder: images plus a cameras.json, optional depth maps.

    ROOT/<scene>/images/<name>.png ...
    ROOT/<scene>/cameras.json       {"frames": [{"image": "<name>.png", "extrinsic": 3x4
                                    world-to-camera (OpenCV), "intrinsic": 3x3 (pixels of
                                    the image), ...}]} -- the file `rvggt reconstruct` writes
    ROOT/<scene>/depth/<stem>.npy   optional float depth [H, W] in metres (0 = none), or
    ROOT/<scene>/depth/<stem>.png   16-bit with depth/depth_scale.json {"scale": s} (depth =
                                    value x s, `rvggt reconstruct`'s format)
    ROOT/<scene>/points.ply         optional ground-truth cloud

ROOT itself may be the scene (ROOT/cameras.json).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene, need_file
from rvggt_jax.eval.datasets.files import save_image

NAME = "folder"


def list_scenes(root: Path) -> list[str]:
    if (root / "cameras.json").is_file():
        return ["."]
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "cameras.json").is_file())
    if not names:
        raise DatasetError(f"no cameras.json in {root} or its sub-folders")
    return names


def _read_depth(path: Path) -> np.ndarray:
    if path.suffix == ".npy":
        return np.load(path).astype(np.float32)
    from rvggt_jax.eval.datasets.files import read_depth_u16

    scale = json.loads(need_file(path.parent / "depth_scale.json", "depth scale").read_text())["scale"]
    return read_depth_u16(path, float(scale))


def read_scene(root: Path, name: str, **_) -> Scene:
    d = root / name
    doc_path = need_file(d / "cameras.json", "cameras file")
    try:
        frames = json.loads(doc_path.read_text())["frames"]
        names = [f["image"] for f in frames]
        ext = np.array([f["extrinsic"] for f in frames], dtype=np.float64)
        ks = np.array([f["intrinsic"] for f in frames], dtype=np.float64)
    except (ValueError, KeyError, TypeError) as e:
        raise DatasetError(f"malformed cameras file {doc_path}: {e}") from None
    if not names or ext.shape[1:] not in ((3, 4), (4, 4)) or ks.shape[1:] != (3, 3):
        raise DatasetError(f"cameras file needs frames with a 3x4 extrinsic and a 3x3 intrinsic: {doc_path}")
    paths = []
    for n in names:
        cands = [d / "images" / n, d / n]
        hit = next((c for c in cands if c.is_file()), None)
        if hit is None:
            raise DatasetError(f"missing image listed in {doc_path.name}: {cands[0]}")
        paths.append(hit)
    depth = None
    if (d / "depth").is_dir():
        depth = []
        for p in paths:
            npy, png = d / "depth" / f"{p.stem}.npy", d / "depth" / f"{p.stem}.png"
            depth.append(npy if npy.exists() or not png.exists() else png)
    ply = d / "points.ply"
    return Scene(NAME, name if name != "." else root.name, paths, ext[:, :3], ks, [p.stem for p in paths], depth,
                 _read_depth if depth else None, None, ply if ply.is_file() else None)


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name> with float depth
    (.npy) and its exact points as points.ply."""
    from rvggt_jax.io.ply import write_ply

    d = root / scene.name
    (d / "images").mkdir(parents=True, exist_ok=True)
    (d / "depth").mkdir(exist_ok=True)
    frames = []
    for i, img in enumerate(scene.images):
        n = f"frame_{i:04d}.png"
        save_image(d / "images" / n, img)
        np.save(d / "depth" / f"frame_{i:04d}.npy", scene.depth[i])
        frames.append(dict(image=n, extrinsic=scene.extrinsics[i].tolist(), intrinsic=scene.intrinsics[i].tolist(),
                           width=int(img.shape[1]), height=int(img.shape[0])))
    (d / "cameras.json").write_text(json.dumps({"frames": frames}, indent=1))
    write_ply(d / "points.ply", scene.cloud()[0])
    return d
