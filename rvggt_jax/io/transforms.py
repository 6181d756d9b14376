"""`transforms.json` in nerfstudio's format ("nerfstudio data format": docs.nerf.studio,
Data conventions), for `ns-train splatfacto --data OUT` and other nerfstudio-format
readers: `camera_model`, per-frame `file_path`, `transform_matrix` (4x4 camera-to-world,
OpenGL camera axes: x right, y up, z back), intrinsics `fl_x, fl_y, cx, cy, w, h` (at the
top level when every frame shares them, else in each frame, as the format allows) and
`ply_file_path` (the initial points of splatfacto).

Our cameras are world-to-camera with OpenCV axes (x right, y down, z forward): the
camera-to-world matrix is their inverse, its y and z camera axes flipped
(`opengl_camera_to_world`). The world frame is left as it is (nerfstudio orients and
centres it itself), so the PLY's points stay where the cameras see them.
"""

from __future__ import annotations

import json
import os
from typing import Sequence

import numpy as np

from rvggt_jax.io.cameras import check_cameras

__all__ = ["OPENCV_TO_OPENGL", "opengl_camera_to_world", "write_transforms_json"]

PathLike = str | os.PathLike

# camera axes OpenCV (x right, y down, z forward) -> OpenGL / nerfstudio (x right, y up, z back)
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def opengl_camera_to_world(extrinsic: np.ndarray) -> np.ndarray:
    """World-to-camera [..., 3, 4] (OpenCV axes) -> camera-to-world [..., 4, 4] with
    OpenGL camera axes (nerfstudio's `transform_matrix`)."""
    e = np.asarray(extrinsic, dtype=np.float64)
    r, t = e[..., :3, :3], e[..., :3, 3]
    c2w = np.zeros(e.shape[:-2] + (4, 4))
    c2w[..., :3, :3] = np.swapaxes(r, -1, -2)
    c2w[..., :3, 3] = -np.einsum("...ji,...j->...i", r, t)
    c2w[..., 3, 3] = 1.0
    return c2w @ OPENCV_TO_OPENGL


def write_transforms_json(path: PathLike, file_paths: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                          sizes: Sequence[tuple[int, int]], ply_file_path: str | None = None) -> dict:
    """Write nerfstudio's `transforms.json` to `path` and return it.

    file_paths [S]: each image's path as nerfstudio should open it (relative to the
    folder of `path`, or absolute); extrinsics [S, 3, 4] world-to-camera (OpenCV);
    intrinsics [S, 3, 3] pinhole in the pixels of sizes [S] = (width, height) of the
    images at `file_paths`; ply_file_path: the point cloud, relative like file_paths."""
    e, k = check_cameras(file_paths, extrinsics, intrinsics, sizes)
    c2w = opengl_camera_to_world(e)
    per_frame = [dict(fl_x=float(k[i, 0, 0]), fl_y=float(k[i, 1, 1]), cx=float(k[i, 0, 2]), cy=float(k[i, 1, 2]),
                      w=int(sizes[i][0]), h=int(sizes[i][1])) for i in range(len(file_paths))]
    shared = all(f == per_frame[0] for f in per_frame)
    doc: dict = {"camera_model": "OPENCV"}  # (no distortion coefficients: pinhole)
    if shared:
        doc.update(per_frame[0])
    doc["frames"] = [dict(file_path=str(p), transform_matrix=c2w[i].tolist(), **({} if shared else per_frame[i]))
                     for i, p in enumerate(file_paths)]
    if ply_file_path is not None:
        doc["ply_file_path"] = str(ply_file_path)
    with open(path, "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")
    return doc
