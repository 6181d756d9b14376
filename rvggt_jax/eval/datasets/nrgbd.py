"""NRGBD (Neural RGB-D Surface Reconstruction, Azinovic et al. 2022) as distributed:

    ROOT/<scene>/images/img0.png ...       RGB
    ROOT/<scene>/depth/depth0.png ...      uint16 millimetres, 0 = no depth
    ROOT/<scene>/poses.txt                 4 rows per frame: 4x4 camera-to-world, OpenGL
                                           axes (x right, y up, z backwards); NaN = invalid
    ROOT/<scene>/focal.txt                 the focal length in pixels (optional)

Poses are converted to OpenCV (c2w @ diag(1, -1, -1, 1)) as CUT3R's `NRGBD` loader,
which RegimeVGGT's `eval/eval_7andN.py` uses. That loader hard-codes f = 554.256...,
c = (320, 240) at 640x480; here focal.txt is used when present (principal point at the
image centre), else that constant scaled to the image. Depth above 10 m or below 1 mm
is no depth. Frames whose pose is not finite are dropped (the loader would keep them
with an identity pose).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene, need_file
from rvggt_jax.eval.datasets.files import c2w_to_w2c, read_depth_u16, save_image, w2c_to_c2w, write_depth_u16

NAME = "nrgbd"
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
FOCAL = 554.2562584220408  # 320 / tan(30 deg): the protocol's constant at 640x480


def read_depth(path: Path) -> np.ndarray:
    """[H, W] metres; above 10 m and below 1 mm is no depth (0), as the protocol."""
    d = read_depth_u16(path, 1e-3)
    d[(d > 10.0) | (d < 1e-3)] = 0.0
    return d


def list_scenes(root: Path) -> list[str]:
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "poses.txt").exists())
    if not names:
        raise DatasetError(f"no NRGBD scene folder (with poses.txt) in {root}")
    return names


def read_scene(root: Path, name: str, **_) -> Scene:
    d = root / name
    if not d.is_dir():
        raise DatasetError(f"missing NRGBD scene folder: {d}")
    try:
        poses = np.array(need_file(d / "poses.txt", "camera poses").read_text().split(), dtype=np.float64)
        focal = float((d / "focal.txt").read_text().split()[0]) if (d / "focal.txt").is_file() else None
    except (ValueError, IndexError):
        raise DatasetError(f"malformed poses.txt or focal.txt in {d}") from None
    if poses.size % 16:
        raise DatasetError(f"poses.txt must hold 4x4 matrices (16 numbers each), found {poses.size} numbers: {d}")
    poses = poses.reshape(-1, 4, 4)
    imgs = sorted((d / "images").glob("img*.png"), key=lambda p: int(re.sub(r"\D", "", p.stem) or 0))
    if not imgs:
        raise DatasetError(f"no images/img*.png in {d}")
    if len(imgs) > len(poses):
        raise DatasetError(f"{len(imgs)} images but {len(poses)} poses in {d / 'poses.txt'}")
    from PIL import Image

    with Image.open(imgs[0]) as im:
        w, h = im.size
    if focal is None:
        fx, fy = FOCAL * w / 640, FOCAL * h / 480
    else:
        fx = fy = focal
    k = np.array([[fx, 0, w / 2.0], [0, fy, h / 2.0], [0, 0, 1.0]])
    keep = [i for i, p in enumerate(imgs) if np.isfinite(poses[int(re.sub(r"\D", "", p.stem))]).all()]
    ids = [re.sub(r"\D", "", imgs[i].stem) for i in keep]
    ext = np.stack([c2w_to_w2c(poses[int(j)] @ GL_TO_CV) for j in ids])
    return Scene(NAME, name, [imgs[i] for i in keep], ext, np.repeat(k[None], len(keep), axis=0), ids,
                 [d / "depth" / f"depth{j}.png" for j in ids], read_depth, None)


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` (square pixels, principal point at
    the image centre) as ROOT/<name>."""
    s, h, w = scene.depth.shape
    k = scene.intrinsics[0]
    if not (np.allclose(scene.intrinsics, k) and np.isclose(k[0, 0], k[1, 1]) and np.allclose(k[:2, 2], [w / 2, h / 2])):
        raise ValueError("NRGBD stores one focal length: the scene needs fx = fy and the principal point at the centre")
    d = root / scene.name
    (d / "images").mkdir(parents=True, exist_ok=True)
    (d / "depth").mkdir(exist_ok=True)
    (d / "focal.txt").write_text(f"{k[0, 0]:.10g}\n")
    rows = []
    for i in range(s):
        save_image(d / "images" / f"img{i}.png", scene.images[i])
        write_depth_u16(d / "depth" / f"depth{i}.png", scene.depth[i], 1e-3)
        gl = w2c_to_c2w(scene.extrinsics[i]) @ GL_TO_CV
        rows += [" ".join(f"{x:.10g}" for x in r) for r in gl]
    (d / "poses.txt").write_text("\n".join(rows) + "\n")
    return d
