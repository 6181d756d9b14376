"""Triangulation of tracks with known cameras, and reprojection errors (pure numpy).

Cameras are world-to-camera extrinsics [S, 3, 4] (OpenCV axes) and pinhole
intrinsics [S, 3, 3]; tracks are pixel positions [S, N, 2] with a mask [S, N] of the
observations to use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Triangulated", "mean_reprojection_error", "project", "reprojection_errors", "triangulate",
           "triangulate_tracks", "triangulation_angles"]


def project(extrinsic: np.ndarray, intrinsic: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [S, N, 2] and camera-frame depths [S, N] of world points [N, 3] in S cameras."""
    e = np.asarray(extrinsic, np.float64)
    k = np.asarray(intrinsic, np.float64)
    cam = np.einsum("sij,nj->sni", e[:, :, :3], np.asarray(points, np.float64)) + e[:, None, :, 3]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.einsum("sij,snj->sni", k, cam)
        uv = uv[..., :2] / uv[..., 2:3]
    return uv, z


def reprojection_errors(extrinsic, intrinsic, points, tracks) -> np.ndarray:
    """Pixel distance [S, N] between each track position [S, N, 2] and the projection of
    its point [N, 3] (inf behind the camera)."""
    uv, z = project(extrinsic, intrinsic, points)
    err = np.linalg.norm(uv - np.asarray(tracks, np.float64), axis=-1)
    return np.where(z > 0, err, np.inf)


def mean_reprojection_error(extrinsic, intrinsic, points, tracks, mask) -> float:
    """Mean pixel reprojection error over the observations in `mask` [S, N] (NaN if none)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return float("nan")
    return float(reprojection_errors(extrinsic, intrinsic, points, tracks)[mask].mean())


def triangulate(extrinsic: np.ndarray, intrinsic: np.ndarray, tracks: np.ndarray,
                mask: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation: world points [N, 3] of tracks [S, N, 2] seen in the
    observations of `mask` [S, N] (NaN for a track with fewer than 2).

    Each observation gives two linear equations in the homogeneous point X; the point is
    the smallest eigenvector of the sum of their normal matrices (4 x 4 per track, all
    tracks at once). The equations are written in normalised image coordinates (K^-1 x),
    which keeps them well conditioned without a separate normalisation step."""
    e = np.asarray(extrinsic, np.float64)
    k = np.asarray(intrinsic, np.float64)
    m = np.asarray(mask, bool)
    s, n = m.shape
    xy = np.concatenate([np.asarray(tracks, np.float64), np.ones((s, n, 1))], axis=-1)
    ray = np.einsum("sij,snj->sni", np.linalg.inv(k), np.where(m[..., None], xy, 0.0))
    # rows x * P3 - P1 and y * P3 - P2 of the normalised projection P = [R | t]
    r1 = ray[..., 0:1] * e[:, None, 2] - e[:, None, 0]  # [S, N, 4]
    r2 = ray[..., 1:2] * e[:, None, 2] - e[:, None, 1]
    w = m[..., None, None].astype(np.float64)
    a = np.sum(w * (r1[..., :, None] * r1[..., None, :] + r2[..., :, None] * r2[..., None, :]), axis=0)
    _, vec = np.linalg.eigh(a)  # ascending eigenvalues: column 0 is the least-squares solution
    hom = vec[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = hom[:, :3] / hom[:, 3:4]
    pts[m.sum(axis=0) < 2] = np.nan
    return pts


def triangulation_angles(extrinsic: np.ndarray, points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Largest angle (degrees) [N] between two rays from the cameras that observe a point
    (`mask` [S, N]) to it (points [N, 3]); 0 with fewer than two observations. A small
    angle means the point's depth is barely constrained: a little noise moves it far."""
    e = np.asarray(extrinsic, np.float64)
    centers = -np.einsum("sji,sj->si", e[:, :, :3], e[:, :, 3])  # -R^T t
    d = np.asarray(points, np.float64)[None] - centers[:, None]  # [S, N, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    m = np.asarray(mask, bool)
    lowest = np.ones(m.shape[1])
    for i in range(len(e)):  # one camera against all: [S, N] at a time, not [S, S, N]
        cos = np.einsum("nk,snk->sn", d[i], d)
        cos = np.where(m[i][None] & m & np.isfinite(cos), cos, 1.0)
        lowest = np.minimum(lowest, cos.min(axis=0))
    return np.degrees(np.arccos(np.clip(lowest, -1.0, 1.0)))


@dataclass(frozen=True, eq=False)
class Triangulated:
    """The tracks that triangulated well.

    points   [M, 3] float64 world points
    tracks   [S, M, 2] float64 their pixel positions, mask [S, M] bool the observations
             kept (inliers; at least `min_views` per point)
    index    [M] int64 the column of each in the input tracks
    """

    points: np.ndarray
    tracks: np.ndarray
    mask: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def triangulate_tracks(extrinsic, intrinsic, tracks, mask, *, max_error: float = 8.0,
                       min_views: int = 2, min_angle_deg: float = 0.0) -> Triangulated:
    """Triangulate tracks [S, N, 2] over their observations `mask` [S, N], then drop the
    observations that reproject more than `max_error` pixels away or lie behind their
    camera (track-head mistakes, occlusions the visibility missed), re-triangulate from
    the rest, and keep the points still seen by `min_views` (>= 2) inlier observations
    whose rays meet at `min_angle_deg` degrees at least (`triangulation_angles`)."""
    if min_views < 2:
        raise ValueError(f"a point needs at least 2 views; got min_views={min_views}")
    tracks = np.asarray(tracks, np.float64)
    m = np.asarray(mask, bool).copy()
    pts = triangulate(extrinsic, intrinsic, tracks, m)
    for _ in range(2):  # the second pass re-checks the re-triangulated points
        err = reprojection_errors(extrinsic, intrinsic, pts, tracks)
        m &= np.isfinite(err) & (err <= max_error)
        m[:, m.sum(axis=0) < min_views] = False
        pts = triangulate(extrinsic, intrinsic, tracks, m)
    err = reprojection_errors(extrinsic, intrinsic, pts, tracks)
    m &= np.isfinite(err) & (err <= max_error)
    ok = (m.sum(axis=0) >= min_views) & np.isfinite(pts).all(axis=1)
    if min_angle_deg > 0:
        ok &= triangulation_angles(extrinsic, np.nan_to_num(pts), m) >= min_angle_deg
    keep = np.flatnonzero(ok)
    return Triangulated(points=pts[keep], tracks=tracks[:, keep], mask=m[:, keep], index=keep)
