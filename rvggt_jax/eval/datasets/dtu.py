"""DTU MVS in the MVSNet test layout (the form DTU is usually evaluated from), plus the
official ground-truth point clouds:

    ROOT/scan<N>/images/00000000.jpg ...
    ROOT/scan<N>/cams/00000000_cam.txt     "extrinsic" + 4x4 world-to-camera,
                                           "intrinsic" + 3x3 (pixels of the images),
                                           then depth_min depth_interval
    ROOT/Points/stl/stl<NNN>_total.ply     ground-truth points (optional; pose-only
                                           evaluation does not need it)
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene, need_file
from rvggt_jax.eval.datasets.files import save_image

NAME = "dtu"
TEST_SCANS = (1, 4, 9, 10, 11, 12, 13, 15, 23, 24, 29, 32, 33, 34, 48, 49, 62, 75, 77, 110, 114, 118)
"""The 22 evaluation scans of MVSNet's DTU split."""


def list_scenes(root: Path) -> list[str]:
    names = [p.name for p in root.iterdir() if p.is_dir() and re.fullmatch(r"scan\d+", p.name) and (p / "cams").is_dir()]
    if not names:
        raise DatasetError(f"no DTU scan folder (scan<N>/ with cams/) in {root}")
    return sorted(names, key=lambda n: int(n[4:]))


def read_cam(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """An MVSNet cam.txt -> (extrinsic [3, 4] world-to-camera, intrinsic [3, 3])."""
    words = need_file(path, "camera file").read_text().split()
    try:
        e = np.array(words[words.index("extrinsic") + 1:][:16], dtype=np.float64).reshape(4, 4)
        k = np.array(words[words.index("intrinsic") + 1:][:9], dtype=np.float64).reshape(3, 3)
    except ValueError:
        raise DatasetError(f"malformed camera file (needs 'extrinsic' 4x4 and 'intrinsic' 3x3): {path}") from None
    return e[:3], k


def read_scene(root: Path, name: str, **_) -> Scene:
    d = root / name
    if not d.is_dir():
        raise DatasetError(f"missing DTU scan folder: {d}")
    imgs = sorted(p for p in (d / "images").glob("*") if p.suffix.lower() in (".jpg", ".png"))
    if not imgs:
        raise DatasetError(f"no images in {d / 'images'}")
    ext, ks = zip(*(read_cam(d / "cams" / f"{p.stem}_cam.txt") for p in imgs))
    m = re.fullmatch(r"scan(\d+)", name)
    ply = root / "Points" / "stl" / f"stl{int(m.group(1)):03d}_total.ply" if m else None
    return Scene(NAME, name, imgs, np.stack(ext), np.stack(ks), [p.stem for p in imgs],
                 points_path=ply if ply is not None and ply.exists() else None)


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/scan<N> (N from the digits of
    its name) with its exact points as Points/stl/stl<NNN>_total.ply."""
    from rvggt_jax.io.ply import write_ply

    digits = re.sub(r"\D", "", scene.name) or "1"
    n = int(digits)
    d = root / f"scan{n}"
    (d / "images").mkdir(parents=True, exist_ok=True)
    (d / "cams").mkdir(exist_ok=True)
    for i, img in enumerate(scene.images):
        save_image(d / "images" / f"{i:08d}.jpg", img)
        e = np.vstack([scene.extrinsics[i], [0, 0, 0, 1]])
        text = "extrinsic\n" + "\n".join(" ".join(f"{x:.10g}" for x in r) for r in e)
        text += "\n\nintrinsic\n" + "\n".join(" ".join(f"{x:.10g}" for x in r) for r in scene.intrinsics[i])
        text += "\n\n2.0 0.01\n"
        (d / "cams" / f"{i:08d}_cam.txt").write_text(text)
    (root / "Points" / "stl").mkdir(parents=True, exist_ok=True)
    write_ply(root / "Points" / "stl" / f"stl{n:03d}_total.ply", scene.cloud()[0])
    return d
