"""Alignments used by the evaluation protocols before a prediction is scored.

A prediction of VGGT lives in the first camera's frame at an arbitrary scale, so every
protocol first brings it onto the ground truth:

- `umeyama`: the least-squares similarity Sim(3) `dst ~ s R src + t` between paired
  points (Umeyama 1991; what evo's `align(correct_scale=True)` and FastVGGT's
  `umeyama_alignment` compute), on camera centres or on points;
- `median_scale_shift`: the 7 Scenes / NRGBD protocol (CUT3R's `Regr3D_t_ScaleShiftInv`,
  used by RegimeVGGT `eval/eval_7andN.py`): shift z by the median depth, scale by the
  ratio of median distances to the median centre;
- `icp_point_to_point`: rigid ICP with a correspondence distance cut-off (the protocol
  runs Open3D's point-to-point ICP, threshold 0.1, identity start, 30 iterations);
- `bbox_scale`: FastVGGT's ScanNet alignment (`align_point_clouds_scale`): centre and
  scale by the bounding boxes' diagonals, no rotation;
- `voxel_downsample`: Open3D's `voxel_down_sample` (mean point of each occupied voxel).

Everything is numpy, float64 inside. ICP and voxel averaging are written here with
scipy's cKDTree rather than importing Open3D: Open3D is a large binary dependency for
two short loops, and writing them down makes the tolerances explicit.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["apply_sim3", "bbox_scale", "icp_point_to_point", "median_scale_shift", "sim3_matrix", "umeyama",
           "voxel_downsample"]


def _points(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be [N, 3] points; got shape {a.shape}")
    return a


def umeyama(src, dst, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity from `src` [N, 3] to `dst` [N, 3] (paired rows).

    Minimises sum_i |dst_i - (s R src_i + t)|^2 over s > 0, R in SO(3), t (Umeyama,
    "Least-squares estimation of transformation parameters between two point patterns",
    PAMI 1991): with centred clouds X (src), Y (dst) and U D V^T = svd(Y^T X / N),
    R = U S V^T (S flips the last axis when det(U) det(V) < 0), s = tr(D S) / var(X),
    t = mean(dst) - s R mean(src). `with_scale=False` gives the rigid SE(3) fit (s = 1).

    Returns (s, R [3, 3], t [3]). Needs N >= 3 points not all on one line."""
    src, dst = _points(src, "src"), _points(dst, "dst")
    if src.shape != dst.shape:
        raise ValueError(f"src {src.shape} and dst {dst.shape} must pair up row by row")
    n = len(src)
    if n < 3:
        raise ValueError(f"a Sim(3) alignment needs at least 3 point pairs; got {n}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, yd = src - mu_s, dst - mu_d
    var_s = float((xs ** 2).sum() / n)
    if var_s <= 1e-20:
        raise ValueError("cannot align: the source points all coincide")
    u, d, vt = np.linalg.svd(yd.T @ xs / n)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[-1] = -1.0
    r = u @ np.diag(sign) @ vt
    s = float((d * sign).sum() / var_s) if with_scale else 1.0
    t = mu_d - s * r @ mu_s
    return s, r, t


def sim3_matrix(s: float, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[4, 4] matrix of x -> s R x + t."""
    m = np.eye(4)
    m[:3, :3] = s * np.asarray(r, np.float64)
    m[:3, 3] = t
    return m


def apply_sim3(points, s: float, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """s R p + t for points [..., 3] -> [..., 3] float64."""
    p = np.asarray(points, np.float64)
    return s * p @ np.asarray(r, np.float64).T + np.asarray(t, np.float64)


def median_scale_shift(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    """The 7 Scenes / NRGBD normalisation (CUT3R `Regr3D_t_ScaleShiftInv`, gt_scale=True).

    pred [N, 3], gt [N, 3]: valid points of all views, both in the first camera's frame.
    Each cloud's z is shifted by its own median z; then the median distance of each
    cloud to its (per-axis) median centre is taken, and pred is multiplied by
    gt_scale / pred_scale (pred_scale clipped to [1e-3, 1e3]). Returns (pred', gt') [N, 3]."""
    pred, gt = _points(pred, "pred").copy(), _points(gt, "gt").copy()
    pred[:, 2] -= np.median(pred[:, 2])
    gt[:, 2] -= np.median(gt[:, 2])

    def scale(p):
        return float(np.median(np.linalg.norm(p - np.median(p, axis=0), axis=1)))

    pred_scale = float(np.clip(scale(pred), 1e-3, 1e3))
    return pred * (scale(gt) / pred_scale), gt


def icp_point_to_point(src, dst, threshold: float, init: np.ndarray | None = None, max_iter: int = 30,
                       rel_fitness: float = 1e-6, rel_rmse: float = 1e-6) -> np.ndarray:
    """Rigid point-to-point ICP of `src` [N, 3] onto `dst` [M, 3] -> [4, 4] transform.

    Open3D's `registration_icp(..., TransformationEstimationPointToPoint())` loop with
    its default `ICPConvergenceCriteria`: pair every transformed source point with its
    nearest destination point closer than `threshold`; up to `max_iter` times, re-solve
    the rigid transform on those pairs (Kabsch = `umeyama(with_scale=False)`), apply it,
    re-pair, and stop once fitness (paired fraction of the source) and inlier RMSE both
    change by less than `rel_fitness` / `rel_rmse` (absolute differences, as Open3D)."""
    src, dst = _points(src, "src"), _points(dst, "dst")
    tree = cKDTree(dst)
    total = np.eye(4) if init is None else np.asarray(init, np.float64).copy()

    def pair(t):
        cur = src @ t[:3, :3].T + t[:3, 3]
        dist, idx = tree.query(cur, distance_upper_bound=threshold, workers=-1)
        keep = np.isfinite(dist)
        fit = float(keep.mean())
        rmse = float(np.sqrt(np.mean(dist[keep] ** 2))) if keep.any() else 0.0
        return cur, idx, keep, fit, rmse

    cur, idx, keep, fit, rmse = pair(total)
    for _ in range(max_iter):
        if keep.sum() < 3:
            break
        _, r, t = umeyama(cur[keep], dst[idx[keep]], with_scale=False)
        total = sim3_matrix(1.0, r, t) @ total
        prev_fit, prev_rmse = fit, rmse
        cur, idx, keep, fit, rmse = pair(total)
        if abs(prev_fit - fit) < rel_fitness and abs(prev_rmse - rmse) < rel_rmse:
            break
    return total


def bbox_scale(pred, gt, pred_bounds: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, float]:
    """FastVGGT's ScanNet alignment: scale pred [N, 3] about its bounding-box centre by
    diag(gt bbox) / diag(pred bbox) and move that centre onto gt's [M, 3] bounding-box
    centre. `pred_bounds` = (min [3], max [3]) of a larger cloud that pred is a subset
    of (the box is then that cloud's). Returns (aligned pred [N, 3], scale)."""
    pred, gt = _points(pred, "pred"), _points(gt, "gt")
    plo, phi = (pred.min(0), pred.max(0)) if pred_bounds is None else pred_bounds
    glo, ghi = gt.min(0), gt.max(0)
    pdiag, gdiag = np.linalg.norm(phi - plo), np.linalg.norm(ghi - glo)
    s = 1.0 if pdiag < 1e-8 else float(gdiag / pdiag)
    return (pred - (phi + plo) / 2) * s + (ghi + glo) / 2, s


def voxel_downsample(points, voxel: float) -> np.ndarray:
    """Mean point of each occupied voxel of size `voxel` (Open3D's grid: voxel
    boundaries at min_bound - voxel/2 + k * voxel). points [N, 3] -> [M, 3], sorted by
    voxel index."""
    p = _points(points, "points")
    if len(p) == 0:
        return p
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive; got {voxel}")
    origin = p.min(0) - voxel / 2
    keys = np.floor((p - origin) / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, p)
    return sums / counts[:, None]
