"""7 Scenes (Microsoft RGB-D Dataset 7-Scenes) as the evaluation reads it:

    ROOT/<scene>/TestSplit.txt                      "sequence2" lines: the test sequences
    ROOT/<scene>/seq-02/frame-000000.color.png       640x480 RGB
    ROOT/<scene>/seq-02/frame-000000.depth.proj.png  depth registered to the colour camera
                                                     (SimpleRecon's), uint16 millimetres
    ROOT/<scene>/seq-02/frame-000000.depth.png       (the raw Kinect depth, used if the
                                                     .depth.proj.png files are absent)
    ROOT/<scene>/seq-02/frame-000000.pose.txt        4x4 camera-to-world

Scenes are named `<scene>/seq-NN`; `list_scenes` gives every test sequence of every
scene (TestSplit.txt), as CUT3R's `SevenScenes` loader that RegimeVGGT's
`eval/eval_7andN.py` uses. Calibration, as that loader: with the registered depth,
SimpleRecon's f = 525, c = (320, 240) at 640x480; with raw depth, the Kinect depth
camera's nominal f = 585. Scaled to the image size. Depth of 65535, above 10 m or below
1 mm is no depth.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene
from rvggt_jax.eval.datasets.files import (c2w_to_w2c, read_depth_u16, read_matrix, save_image, w2c_to_c2w,
                                           write_depth_u16, write_matrix)

NAME = "7scenes"
FOCAL_PROJ, FOCAL_RAW, CX, CY, W0, H0 = 525.0, 585.0, 320.0, 240.0, 640, 480


def intrinsics_for(width: int, height: int, focal: float = FOCAL_PROJ) -> np.ndarray:
    """The 7 Scenes camera [3, 3] (f = 525 with registered depth, 585 raw) scaled to an
    image of width x height."""
    sx, sy = width / W0, height / H0
    return np.array([[focal * sx, 0, CX * sx], [0, focal * sy, CY * sy], [0, 0, 1.0]])


def read_depth(path: Path) -> np.ndarray:
    """[H, W] metres; 65535, > 10 m and < 1 mm are no depth (0), as the protocol."""
    d = read_depth_u16(path, 1e-3, invalid=65535)
    d[(d > 10.0) | (d < 1e-3)] = 0.0
    return d


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
    return [f"{d.name}/{seq}" for d in dirs for seq in _test_sequences(d)]


def read_scene(root: Path, name: str, **_) -> Scene:
    seq = root / name
    if not seq.is_dir():
        raise DatasetError(f"missing 7 Scenes sequence folder: {seq}")
    colors = sorted(seq.glob("frame-*.color.png"))
    if not colors:
        raise DatasetError(f"no frame-*.color.png in {seq}")
    registered = (seq / colors[0].name.replace(".color.png", ".depth.proj.png")).exists()
    suffix = ".depth.proj.png" if registered else ".depth.png"
    ext, ids, depths = [], [], []
    for c in colors:
        stem = c.name[: -len(".color.png")]
        c2w = read_matrix(seq / f"{stem}.pose.txt", "camera pose")
        ext.append(c2w_to_w2c(c2w))
        ids.append(stem)
        depths.append(seq / f"{stem}{suffix}")
    from PIL import Image

    with Image.open(colors[0]) as im:
        w, h = im.size
    k = np.repeat(intrinsics_for(w, h, FOCAL_PROJ if registered else FOCAL_RAW)[None], len(colors), axis=0)
    return Scene(NAME, name, colors, np.stack(ext), k, ids, depths, read_depth, None,
                 meta=dict(registered_depth=registered))


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name>/seq-01 (its only,
    test, sequence) with registered depth (.depth.proj.png). Its cameras must be the
    7 Scenes calibration at its size (f = 525 x width / 640)."""
    s, h, w = scene.depth.shape
    if not np.allclose(scene.intrinsics, intrinsics_for(w, h)[None], rtol=1e-6, atol=1e-6):
        raise ValueError("7 Scenes has a fixed calibration: make the scene with focal=(525*width/640, 525*height/480)")
    d = root / scene.name
    seq = d / "seq-01"
    seq.mkdir(parents=True, exist_ok=True)
    (d / "TestSplit.txt").write_text("sequence1\n")
    (d / "TrainSplit.txt").write_text("sequence2\n")
    for i in range(s):
        save_image(seq / f"frame-{i:06d}.color.png", scene.images[i])
        write_depth_u16(seq / f"frame-{i:06d}.depth.proj.png", scene.depth[i], 1e-3, invalid=65535)
        write_matrix(seq / f"frame-{i:06d}.pose.txt", w2c_to_c2w(scene.extrinsics[i]))
    return seq
