"""The pycolmap bridge: a `pycolmap.Reconstruction` of our cameras, points and tracks,
pycolmap's bundle adjustment on it, and the refined arrays read back.

Each frame is its own camera (VGGT predicts a focal length per frame), or all frames
share camera 1 (`shared_camera`: the median intrinsics), each camera on a trivial rig;
PINHOLE by default, or SIMPLE_PINHOLE / SIMPLE_RADIAL (one focal length f, refined as
one with `refine_focal`; SIMPLE_RADIAL's k stays 0), as `rvggt_jax.io.colmap` writes
them. The gauge (the similarity BA cannot see) is fixed by pycolmap's
TWO_CAMS_FROM_WORLD: the first frame's pose and the scale set by the second frame stay
as predicted, so the refined cameras stay in the model's world frame (frame 0's camera)
and in its units, where the depth maps and points.ply are.

pycolmap is imported when a function here runs (`rvggt_jax.ba.require_pycolmap`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rvggt_jax.ba import quiet_pycolmap, require_pycolmap
from rvggt_jax.geometry import nearest_rotation
from rvggt_jax.io.colmap import colmap_cameras

__all__ = ["Adjusted", "build_pycolmap_reconstruction", "bundle_adjust", "read_back"]

LOSSES = ("cauchy", "soft_l1", "huber", "trivial")


def build_pycolmap_reconstruction(names: Sequence[str], extrinsic: np.ndarray, intrinsic: np.ndarray,
                                  sizes: Sequence[tuple[int, int]], points: np.ndarray, tracks: np.ndarray,
                                  mask: np.ndarray, colors: np.ndarray | None = None, *,
                                  camera_model: str = "PINHOLE", shared_camera: bool = False):
    """A `pycolmap.Reconstruction`: image i+1 (named `names[i]`) with camera i+1
    (`camera_model` of `intrinsic[i]` [S, 3, 3], `sizes[i]` = (width, height); with
    `shared_camera`, camera 1 for every image: `rvggt_jax.io.colmap.colmap_cameras`) and
    pose `extrinsic[i]` [3, 4] world-to-camera; point j+1 at `points[j]` ([M, 3])
    observed at `tracks[i, j]` ([S, M, 2] pixels) wherever `mask[i, j]` ([S, M] bool);
    colors [M, 3] uint8.

    Image i's 2D points are its observations in point order, so the observation of point
    j in image i is its 2D point number `cumsum(mask[i])[j] - 1`."""
    pycolmap = require_pycolmap()
    e = np.asarray(extrinsic, np.float64)
    cams = colmap_cameras(intrinsic, sizes, camera_model, shared_camera)
    m = np.asarray(mask, bool)
    tracks = np.asarray(tracks, np.float64)
    s, n = m.shape
    cols = np.zeros((n, 3), np.uint8) if colors is None else np.asarray(colors, np.uint8)
    rec = pycolmap.Reconstruction()
    for c, ((w, h), params) in enumerate(zip(cams.sizes, cams.params)):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=cams.model, width=w, height=h, camera_id=c + 1,
                                                        params=params.tolist()))
    for i in range(s):
        image = pycolmap.Image(name=names[i], keypoints=tracks[i][m[i]].reshape(-1, 2),
                               camera_id=int(cams.camera_ids[i]), image_id=i + 1)
        pose = np.concatenate([nearest_rotation(e[i, :, :3]), e[i, :, 3:]], axis=1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pose))
    idx = np.cumsum(m, axis=1) - 1  # [S, M] the 2D point number of each observation
    for j in range(n):
        track = pycolmap.Track()
        for i in np.flatnonzero(m[:, j]):
            track.add_element(int(i) + 1, int(idx[i, j]))
        rec.add_point3D(np.asarray(points[j], np.float64), track, cols[j])
    return rec


@dataclass(frozen=True, eq=False)
class Adjusted:
    """Arrays of a bundle-adjusted reconstruction, in the input's order.

    extrinsic [S, 3, 4] world-to-camera, intrinsic [S, 3, 3], points [M, 3] (point j of
    the input); summary: pycolmap's one-line report; usable: pycolmap's verdict on the
    solution."""

    extrinsic: np.ndarray
    intrinsic: np.ndarray
    points: np.ndarray
    summary: str
    usable: bool


def bundle_adjust(rec, *, refine_focal: bool = False, loss: str = "cauchy", loss_scale: float = 1.0,
                  max_iterations: int = 100) -> tuple[str, bool]:
    """Refine the poses and points of the pycolmap reconstruction `rec` in place (and the
    focal lengths with `refine_focal`; the principal point never: it is poorly
    constrained and VGGT's is the image centre by construction). `loss`: the robust
    loss on the reprojection residuals (`LOSSES`; Cauchy by default, because the
    tracker's outliers that survived the filters should not pull the cameras),
    `loss_scale` its scale in pixels. Returns pycolmap's brief report and whether the
    solution is usable."""
    pycolmap = require_pycolmap()
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}; got {loss!r}")
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = refine_focal
    opts.refine_principal_point = False
    opts.refine_extra_params = False  # SIMPLE_RADIAL's k stays 0 (VGGT's cameras are pinholes)
    opts.print_summary = False
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss.upper())
    opts.ceres.loss_function_scale = float(loss_scale)
    opts.ceres.solver_options.max_num_iterations = int(max_iterations)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    with quiet_pycolmap():
        summary = pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()
    rec.update_point_3d_errors()
    brief = summary.brief_report() if hasattr(summary, "brief_report") else str(summary)
    return " ".join(str(brief).split()), bool(getattr(summary, "is_solution_usable", lambda: True)())


def read_back(rec, num_frames: int, num_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(extrinsic [S, 3, 4], intrinsic [S, 3, 3], points [M, 3]) of a reconstruction built
    by `build_pycolmap_reconstruction` (image i+1 = frame i, point j+1 = point j; each
    frame's intrinsic is its camera's, shared or not)."""
    ext = np.stack([np.asarray(rec.image(i + 1).cam_from_world().matrix(), np.float64) for i in range(num_frames)])
    k = np.stack([np.asarray(rec.camera(rec.image(i + 1).camera_id).calibration_matrix(), np.float64)
                  for i in range(num_frames)])
    pts = np.stack([np.asarray(rec.point3D(j + 1).xyz, np.float64) for j in range(num_points)]) if num_points \
        else np.zeros((0, 3))
    return ext, k, pts


def run_bundle_adjustment(names, extrinsic, intrinsic, sizes, points, tracks, mask, colors=None, *,
                          camera_model: str = "PINHOLE", shared_camera: bool = False, **ba_options):
    """Build (`build_pycolmap_reconstruction`: the cameras as `camera_model` and
    `shared_camera` say), adjust (`bundle_adjust`: `ba_options`) and read back:
    `(Adjusted, the pycolmap reconstruction)`. Point ids are 1..M in the input's order
    (pycolmap numbers new points consecutively from 1, which `read_back` relies on;
    checked here)."""
    rec = build_pycolmap_reconstruction(names, extrinsic, intrinsic, sizes, points, tracks, mask, colors,
                                        camera_model=camera_model, shared_camera=shared_camera)
    if sorted(rec.point3D_ids()) != list(range(1, len(points) + 1)):
        raise RuntimeError("pycolmap did not number the points 1..M in order; cannot read them back")
    summary, usable = bundle_adjust(rec, **ba_options)
    e, k, p = read_back(rec, len(names), len(points))
    return Adjusted(extrinsic=e, intrinsic=k, points=p, summary=summary, usable=usable), rec
