"""KITTI odometry sequences, as distributed (data_odometry_color + data_odometry_poses):

    ROOT/sequences/<NN>/image_2/000000.png ...   left colour camera, rectified
    ROOT/sequences/<NN>/calib.txt                "P0: ..." .. "P3: ..." (12 numbers each, a
                                                 row-major 3x4 projection), "Tr: ..."
    ROOT/sequences/<NN>/times.txt                one timestamp (s) per frame (optional here)
    ROOT/poses/<NN>.txt                          one line per frame: 12 numbers, the
                                                 row-major 3x4 camera-to-world pose of the
                                                 left (grey, P0) camera in the first
                                                 camera's frame, OpenCV axes, metres

Only sequences with a poses file are listed (00-10 in the release). Intrinsics of
image_2 are the left 3x3 block of P2. P2 = K [I | t] puts camera 2 at t (about 6 cm to
the side of camera 0, whose P0 = K [I | 0]); the reader moves each pose by t so that the
extrinsics are those of the images read.

`read_kitti_poses` / `write_kitti_poses` read and write a poses file on their own (world-
to-camera [S, 3, 4] in, out), e.g. for a predicted trajectory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene, need_file
from rvggt_jax.eval.datasets.files import c2w_to_w2c, save_image, w2c_to_c2w
from rvggt_jax.eval.datasets.text_table import as_extrinsics, format_floats, numbers, read_rows

__all__ = ["NAME", "list_scenes", "read_calib", "read_kitti_poses", "read_scene", "write", "write_kitti_poses"]

NAME = "kitti"
IMAGE_DIR = "image_2"
ROTATION_TOL = 1e-3  # KITTI prints 6-7 significant digits: far below this off a rotation


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """A KITTI poses file (12 numbers a line: row-major 3x4 camera-to-world) -> world-
    to-camera extrinsics [S, 3, 4] float64. DatasetError naming `path:line` for a line
    without 12 numbers, a non-finite value, or a 3x3 block that is not a rotation."""
    path = Path(path)
    rows = read_rows(path, "KITTI pose", 12)
    if not rows:
        raise DatasetError(f"no pose in {path}")
    c2w = np.zeros((len(rows), 4, 4))
    c2w[:, 3, 3] = 1.0
    for i, (line, tokens) in enumerate(rows):
        c2w[i, :3] = numbers(tokens, path, line, "KITTI pose").reshape(3, 4)
        r = c2w[i, :3, :3]
        off = np.abs(r @ r.T - np.eye(3)).max()
        if off > ROTATION_TOL or np.linalg.det(r) < 0:
            raise DatasetError(f"{path}:{line}: the pose's 3x3 block is not a rotation (|R R^T - I| = {off:.2g}, "
                               f"det = {np.linalg.det(r):.3g})")
    return c2w_to_w2c(c2w)


def write_kitti_poses(path: str | Path, w2c) -> Path:
    """Write world-to-camera extrinsics [S, 3, 4] (or [S, 4, 4]) as a KITTI poses file
    (camera-to-world, 12 numbers a line, exact decimals); returns the path."""
    path = Path(path)
    c2w = w2c_to_c2w(as_extrinsics(w2c))[:, :3]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(format_floats(m) + "\n" for m in c2w))
    return path


def read_calib(path: Path, key: str = "P2") -> tuple[np.ndarray, np.ndarray]:
    """(K [3, 3], t [3]) of projection `key` of a calib.txt, P = K [I | t]."""
    found = {}
    for line, tokens in read_rows(path, "KITTI calibration"):
        name = tokens[0].rstrip(":")
        if name == key:
            if len(tokens) != 13:
                raise DatasetError(f"{path}:{line}: {key} holds 12 numbers (a 3x4 projection), found {len(tokens) - 1}")
            found[key] = numbers(tokens[1:], path, line, f"KITTI calibration {key}").reshape(3, 4)
    if key not in found:
        raise DatasetError(f"no '{key}:' line in {path}")
    p = found[key]
    k = p[:, :3]
    if abs(k[2, 2]) < 1e-12 or np.abs(k[2, :2]).max() > 1e-9 or abs(k[1, 0]) > 1e-9:
        raise DatasetError(f"{path}: {key}'s left 3x3 block is not a pinhole camera matrix: {k.tolist()}")
    return k / k[2, 2], np.linalg.solve(k, p[:, 3])


def _read_times(path: Path, n: int) -> np.ndarray | None:
    if not path.is_file():
        return None
    rows = read_rows(path, "KITTI timestamp", 1)
    if len(rows) != n:
        raise DatasetError(f"{path} holds {len(rows)} timestamps for {n} images")
    return np.array([numbers(t, path, line, "KITTI timestamp")[0] for line, t in rows])


def _poses_path(root: Path, name: str) -> Path:
    return root / "poses" / f"{name}.txt"


def list_scenes(root: Path) -> list[str]:
    seqs = root / "sequences"
    names = sorted(p.name for p in seqs.iterdir() if (p / IMAGE_DIR).is_dir() and _poses_path(root, p.name).is_file()) \
        if seqs.is_dir() else []
    if not names:
        raise DatasetError(f"no KITTI odometry sequence with ground truth under {root}: --dataset kitti reads "
                           f"sequences/<NN>/{IMAGE_DIR}/*.png with poses/<NN>.txt")
    return names


def read_scene(root: Path, name: str, **_) -> Scene:
    seq = root / "sequences" / name
    img_dir = seq / IMAGE_DIR
    if not img_dir.is_dir():
        raise DatasetError(f"missing KITTI image folder: {img_dir}")
    images = sorted(img_dir.glob("*.png"))
    if not images:
        raise DatasetError(f"no .png images in {img_dir}")
    poses = need_file(_poses_path(root, name), "KITTI ground-truth poses")
    w2c = read_kitti_poses(poses)
    if len(w2c) != len(images):
        raise DatasetError(f"{poses} holds {len(w2c)} poses for {len(images)} images in {img_dir}")
    k, offset = read_calib(need_file(seq / "calib.txt", "KITTI calibration"))
    w2c[:, :, 3] += offset  # camera 0 -> camera 2: x_2 = x_0 + t (rectified: same rotation)
    times = _read_times(seq / "times.txt", len(images))
    return Scene(NAME, name, images, w2c, np.repeat(k[None], len(images), axis=0), [p.stem for p in images],
                 meta=dict(timestamps=times, camera=IMAGE_DIR))


def write(scene, root: Path) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as the next free sequence number
    (00, 01, ...) under ROOT/sequences, with poses/<NN>.txt; one camera matrix for the
    whole sequence (P2 = K [I | 0]); returns the sequence folder."""
    k = np.asarray(scene.intrinsics[0], np.float64)
    if not np.allclose(scene.intrinsics, k[None], rtol=0, atol=1e-12):
        raise ValueError("a KITTI sequence has one camera: the scene's intrinsics differ between frames")
    seqs = root / "sequences"
    seqs.mkdir(parents=True, exist_ok=True)
    taken = {p.name for p in seqs.iterdir()}
    name = next(f"{i:02d}" for i in range(len(taken) + 1) if f"{i:02d}" not in taken)
    seq = seqs / name
    (seq / IMAGE_DIR).mkdir(parents=True)
    for i, img in enumerate(scene.images):
        save_image(seq / IMAGE_DIR / f"{i:06d}.png", img)
    right = np.array([-0.54 * k[0, 0], 0.0, 0.0])  # the release's ~0.54 m stereo baseline (cameras 1, 3)
    proj = {"P0": np.c_[k, np.zeros(3)], "P1": np.c_[k, right], "P2": np.c_[k, np.zeros(3)], "P3": np.c_[k, right],
            "Tr": np.eye(4)[:3]}
    (seq / "calib.txt").write_text("".join(f"{n}: {format_floats(p)}\n" for n, p in proj.items()))
    (seq / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(len(scene.images))))
    write_kitti_poses(_poses_path(root, name), scene.extrinsics)
    return seq
