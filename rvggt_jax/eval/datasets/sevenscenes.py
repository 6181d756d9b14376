"""7 Scenes (Microsoft RGB-D Dataset 7-Scenes) as distributed:

    ROOT/<scene>/TestSplit.txt                 "sequence2" lines: the test sequences
    ROOT/<scene>/seq-02/frame-000000.color.png  640x480 RGB
    ROOT/<scene>/seq-02/frame-000000.depth.png  uint16 millimetres, 65535 = no depth
    ROOT/<scene>/seq-02/frame-000000.pose.txt   4x4 camera-to-world

Scenes are named `<scene>/seq-NN`; `list_scenes` gives, per scene folder, its first
test sequence (TestSplit.txt), as the CUT3R / RegimeVGGT protocol (test split, one
sequence per scene). The dataset ships no calibration file: the Kinect's nominal
intrinsics (f = 585, principal point (320, 240) at 640x480) are used, scaled to the
image size.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene
from rvggt_jax.eval.datasets.files import (c2w_to_w2c, read_depth_u16, read_matrix, save_image, w2c_to_c2w,
                                           write_depth_u16, write_matrix)

NAME = "7scenes"
FOCAL, CX, CY, W0, H0 = 585.0, 320.0, 240.0, 640, 480


def intrinsics_for(width: int, height: int) -> np.ndarray:
    """The nominal 7 Scenes camera [3, 3] scaled to an image of width x height."""
    sx, sy = width / W0, height / H0
    return np.array([[FOCAL * sx, 0, CX * sx], [0, FOCAL * sy, CY * sy], [0, 0, 1.0]])


def _test_sequences(scene_dir: Path) -> list[str]:
    split = scene_dir / "TestSplit.txt"
    if not split.is_file():
        raise DatasetError(f"missing test split file: {split}")
    seqs = []
    for line in split.read_text().split():
        m = re.fullmatch(r"sequence(\d+)", line.strip())
        if m:
            seqs.append(f"seq-{int(m.group(1)):02d}")
    if not seqs:
        raise DatasetError(f"no 'sequenceN' line in {split}")
    return seqs


def list_scenes(root: Path) -> list[str]:
    dirs = sorted(p for p in root.iterdir() if p.is_dir() and (p / "TestSplit.txt").exists())
    if not dirs:
        raise DatasetError(f"no 7 Scenes scene folder (with TestSplit.txt) in {root}")
    return [f"{d.name}/{_test_sequences(d)[0]}" for d in dirs]


def read_scene(root: Path, name: str, **_) -> Scene:
    seq = root / name
    if not seq.is_dir():
        raise DatasetError(f"missing 7 Scenes sequence folder: {seq}")
    colors = sorted(seq.glob("frame-*.color.png"))
    if not colors:
        raise DatasetError(f"no frame-*.color.png in {seq}")
    ext, ids, depths = [], [], []
    for c in colors:
        stem = c.name[: -len(".color.png")]
        c2w = read_matrix(seq / f"{stem}.pose.txt", "camera pose")
        ext.append(c2w_to_w2c(c2w))
        ids.append(stem)
        depths.append(seq / f"{stem}.depth.png")
    from PIL import Image

    with Image.open(colors[0]) as im:
        w, h = im.size
    k = np.repeat(intrinsics_for(w, h)[None], len(colors), axis=0)
    return Scene(NAME, name, colors, np.stack(ext), k, ids, depths,
                 lambda p: read_depth_u16(p, 1e-3, invalid=65535), None)


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name>/seq-01 (its only,
    test, sequence). Its cameras must be the nominal 7 Scenes calibration at its size."""
    s, h, w = scene.depth.shape
    if not np.allclose(scene.intrinsics, intrinsics_for(w, h)[None], rtol=1e-6, atol=1e-6):
        raise ValueError("7 Scenes has a fixed calibration: make the scene with focal=585*width/640 and a 4:3 image")
    d = root / scene.name
    seq = d / "seq-01"
    seq.mkdir(parents=True, exist_ok=True)
    (d / "TestSplit.txt").write_text("sequence1\n")
    (d / "TrainSplit.txt").write_text("sequence2\n")
    for i in range(s):
        save_image(seq / f"frame-{i:06d}.color.png", scene.images[i])
        write_depth_u16(seq / f"frame-{i:06d}.depth.png", scene.depth[i], 1e-3, invalid=65535)
        write_matrix(seq / f"frame-{i:06d}.pose.txt", w2c_to_c2w(scene.extrinsics[i]))
    return seq
