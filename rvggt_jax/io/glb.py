"""`scene.glb`: the point cloud and the camera frustums in one glTF binary file (as
upstream's demo exports), for Blender, web viewers and anything that reads glTF.

Axes: glTF is y-up with cameras looking down -z, our world is the first camera's OpenCV
frame (x right, y down, z forward), so every coordinate is multiplied by
`OPENCV_TO_GLTF = diag(1, -1, -1)`: the scene opens upright, seen from the first camera.
Geometry names: `points` (a point cloud with vertex colours) and `camera_000`,
`camera_001`, ... (one frustum mesh per image, coloured from green (first) to red (last)).
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

__all__ = ["OPENCV_TO_GLTF", "frustum_corners", "write_glb"]

OPENCV_TO_GLTF = np.diag([1.0, -1.0, -1.0])


def frustum_corners(extrinsic: np.ndarray, intrinsic: np.ndarray, size: tuple[int, int], depth: float) -> np.ndarray:
    """World points [5, 3] of one camera's frustum: the centre, then the image corners
    (0,0), (W,0), (W,H), (0,H) at `depth` along the viewing axis.

    extrinsic [3, 4] world-to-camera, intrinsic [3, 3] in the pixels of `size` = (W, H)."""
    e = np.asarray(extrinsic, np.float64)
    k = np.asarray(intrinsic, np.float64)
    w, h = size
    pix = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], np.float64)
    cam = (np.linalg.inv(k) @ pix.T).T * depth  # z = depth
    cam = np.concatenate([np.zeros((1, 3)), cam], axis=0)
    r, t = e[:, :3], e[:, 3]
    return (cam - t) @ r  # R^T (x - t), row-wise


def _scene_scale(centers: np.ndarray, points: np.ndarray) -> float:
    """A frustum depth that suits the scene: a tenth of its extent (camera spread or the
    points' robust spread), so frustums are visible but do not swamp the cloud."""
    spans = [float(np.linalg.norm(np.ptp(centers, axis=0)))] if len(centers) > 1 else []
    if len(points):
        lo, hi = np.percentile(points, [5, 95], axis=0)
        spans.append(float(np.linalg.norm(hi - lo)))
    span = max([s for s in spans if np.isfinite(s)] or [1.0])
    return 0.1 * (span if span > 1e-9 else 1.0)


def write_glb(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray, extrinsic: np.ndarray,
              intrinsic: np.ndarray, sizes: Sequence[tuple[int, int]]) -> dict:
    """Write `scene.glb`: points [N, 3] with colors [N, 3] uint8, and a frustum per
    camera from extrinsic [S, 3, 4] (world-to-camera) and intrinsic [S, 3, 3] in the
    pixels of sizes[S] = (W, H). Returns {"points": N, "cameras": S, "frustum_depth": d}."""
    import trimesh

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    cols = np.asarray(colors, np.uint8).reshape(-1, 3)
    e = np.asarray(extrinsic, np.float64)
    centers = -np.einsum("sji,sj->si", e[:, :3, :3], e[:, :3, 3])
    depth = _scene_scale(centers, pts)
    scene = trimesh.Scene()
    if len(pts):
        rgba = np.concatenate([cols, np.full((len(cols), 1), 255, np.uint8)], axis=1)
        scene.add_geometry(trimesh.PointCloud(pts @ OPENCV_TO_GLTF.T, colors=rgba), node_name="points",
                           geom_name="points")
    s = len(e)
    # the four sides (apex, corner i, corner i+1), both windings: visible from inside and out
    sides = [[0, 1 + i, 1 + (i + 1) % 4] for i in range(4)]
    faces = np.array(sides + [[a, c, b] for a, b, c in sides])
    for i in range(s):
        corners = frustum_corners(e[i], intrinsic[i], sizes[i], depth) @ OPENCV_TO_GLTF.T
        mesh = trimesh.Trimesh(vertices=corners, faces=faces, process=False)
        f = i / max(s - 1, 1)
        mesh.visual.face_colors = np.array([int(255 * f), int(200 * (1 - f)), 40, 255], np.uint8)
        scene.add_geometry(mesh, node_name=f"camera_{i:03d}", geom_name=f"camera_{i:03d}")
    with open(path, "wb") as fh:
        fh.write(scene.export(file_type="glb"))
    return dict(points=int(len(pts)), cameras=s, frustum_depth=depth)
