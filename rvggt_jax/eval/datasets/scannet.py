"""ScanNet, frames exported by the official SensReader (the layout FastVGGT's and
RegimeVGGT's ScanNet-50 evaluations read):

    ROOT/<scene>/color/<i>.jpg                      RGB (1296x968 in ScanNet)
    ROOT/<scene>/depth/<i>.png                      uint16 millimetres (640x480), 0 = none
    ROOT/<scene>/pose/<i>.txt                       4x4 camera-to-world; -inf/NaN = invalid
    ROOT/<scene>/intrinsic/intrinsic_color.txt      4x4 (the colour camera)
    ROOT/<scene>/intrinsic/intrinsic_depth.txt      4x4 (the depth camera; optional)
    GT_ROOT/<scene>/<scene>_vh_clean_2.ply          the reconstructed mesh (its vertices
                                                    are the ground-truth cloud)

GT_ROOT defaults to ROOT (`--gt-root` elsewhere). Frames with both an image and a
finite pose are kept, ordered by number (FastVGGT `load_poses` / `build_frame_selection`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene
from rvggt_jax.eval.datasets.files import (c2w_to_w2c, read_depth_u16, read_matrix, save_image, w2c_to_c2w,
                                           write_depth_u16, write_matrix)

NAME = "scannet"


def list_scenes(root: Path) -> list[str]:
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "pose").is_dir())
    if not names:
        raise DatasetError(f"no ScanNet scene folder (with pose/) in {root}")
    return names


def _numbered(folder: Path, pattern: str) -> dict[int, Path]:
    out = {}
    for p in folder.glob(pattern):
        if p.stem.isdigit():
            out[int(p.stem)] = p
    return out


def read_scene(root: Path, name: str, gt_root: Path | None = None, **_) -> Scene:
    d = root / name
    if not d.is_dir():
        raise DatasetError(f"missing ScanNet scene folder: {d}")
    for sub in ("color", "pose"):
        if not (d / sub).is_dir():
            raise DatasetError(f"missing folder: {d / sub}")
    images = {**_numbered(d / "color", "*.jpg"), **_numbered(d / "color", "*.png")}
    poses = _numbered(d / "pose", "*.txt")
    kc = read_matrix(d / "intrinsic" / "intrinsic_color.txt", "colour intrinsics")[:3, :3]
    kd_path = d / "intrinsic" / "intrinsic_depth.txt"
    kd = read_matrix(kd_path, "depth intrinsics")[:3, :3] if kd_path.exists() else kc
    ids, ext = [], []
    for i in sorted(set(images) & set(poses)):
        c2w = read_matrix(poses[i], "camera pose")
        if np.isfinite(c2w).all():
            ids.append(i)
            ext.append(c2w_to_w2c(c2w))
    if not ids:
        raise DatasetError(f"no frame with both an image in {d / 'color'} and a finite pose in {d / 'pose'}")
    n = len(ids)
    ply = (gt_root or root) / name / f"{name}_vh_clean_2.ply"
    return Scene(NAME, name, [images[i] for i in ids], np.stack(ext), np.repeat(kc[None], n, axis=0),
                 [str(i) for i in ids], [d / "depth" / f"{i}.png" for i in ids], lambda p: read_depth_u16(p, 1e-3),
                 np.repeat(kd[None], n, axis=0), ply)


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name> (colour and depth at
    the same size and calibration), with the union of its frames' exact points as
    <name>_vh_clean_2.ply."""
    from rvggt_jax.io.ply import write_ply

    d = root / scene.name
    for sub in ("color", "depth", "pose", "intrinsic"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    k4 = np.eye(4)
    k4[:3, :3] = scene.intrinsics[0]
    write_matrix(d / "intrinsic" / "intrinsic_color.txt", k4)
    write_matrix(d / "intrinsic" / "intrinsic_depth.txt", k4)
    for i in range(len(scene.images)):
        save_image(d / "color" / f"{i}.jpg", scene.images[i])
        write_depth_u16(d / "depth" / f"{i}.png", scene.depth[i], 1e-3)
        write_matrix(d / "pose" / f"{i}.txt", w2c_to_c2w(scene.extrinsics[i]))
    write_ply(d / f"{scene.name}_vh_clean_2.ply", scene.cloud()[0])
    return d
