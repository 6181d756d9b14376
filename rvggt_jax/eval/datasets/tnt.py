"""Tanks and Temples training scenes with their COLMAP reconstruction (the poses
RegimeVGGT's `eval/eval_pose_tnt.py` scores against):

    ROOT/<Scene>/images/<name>.jpg    (or the images directly in ROOT/<Scene>/)
    ROOT/<Scene>/sparse/0/            cameras.bin + images.bin (or .txt)
                                      (also accepted: ROOT/<Scene>/0/ or ROOT/<Scene>/sparse/)

Frames are the model's registered images sorted by name, with a file on disk.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene
from rvggt_jax.eval.datasets.colmap_binary import read_model, write_model_bin
from rvggt_jax.eval.datasets.files import save_image

NAME = "tnt"
TRAINING = ("Barn", "Caterpillar", "Courthouse", "Ignatius", "Meetingroom", "Truck")
_MODEL_DIRS = ("sparse/0", "0", "sparse")


def _model_dir(d: Path) -> Path | None:
    for sub in _MODEL_DIRS:
        m = d / sub
        if (m / "images.bin").is_file() or (m / "images.txt").is_file():
            return m
    return None


def list_scenes(root: Path) -> list[str]:
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and _model_dir(p) is not None)
    if not names:
        raise DatasetError(f"no Tanks and Temples scene folder (with sparse/0/images.bin) in {root}")
    return names


def read_scene(root: Path, name: str, **_) -> Scene:
    d = root / name
    if not d.is_dir():
        raise DatasetError(f"missing Tanks and Temples scene folder: {d}")
    m = _model_dir(d)
    if m is None:
        raise DatasetError(f"missing COLMAP model: {d / 'sparse/0/images.bin'} (or images.txt)")
    paths, ext, ks, ids = [], [], [], []
    for r in read_model(m):
        base = Path(r["name"]).name
        for cand in (d / "images" / r["name"], d / r["name"], d / "images" / base, d / base):
            if cand.is_file():
                paths.append(cand)
                ext.append(r["extrinsic"])
                ks.append(r["intrinsic"])
                ids.append(Path(r["name"]).stem)
                break
    if not paths:
        raise DatasetError(f"none of the model's images is on disk: looked for {d / 'images' / '<name>'}")
    return Scene(NAME, name, paths, np.stack(ext), np.stack(ks), ids)


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name>/images + sparse/0 (binary)."""
    d = root / scene.name
    (d / "images").mkdir(parents=True, exist_ok=True)
    names = [f"{i:06d}.jpg" for i in range(len(scene.images))]
    for n, img in zip(names, scene.images):
        save_image(d / "images" / n, img)
    h, w = scene.images.shape[1:3]
    write_model_bin(d / "sparse" / "0", names, scene.extrinsics, scene.intrinsics, [(w, h)] * len(names))
    return d
