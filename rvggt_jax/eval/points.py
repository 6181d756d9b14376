"""Point-cloud metrics: Accuracy, Completeness, Normal Consistency, Chamfer distance,
and depth AbsRel.

Protocol sources:
- Acc / Comp / NC: the `accuracy` / `completion` functions of the CUT3R / Spann3R
  evaluation code that RegimeVGGT `eval/eval_7andN.py` imports. With nearest neighbours
  from a k-d tree:
    acc  = mean_{p in pred} min_{g in gt} |p - g|     (acc_med: the median)
    comp = mean_{g in gt} min_{p in pred} |g - p|     (comp_med: the median)
    nc1  = mean_{p in pred} |<n_p, n_nn_gt(p)>|,  nc2 = mean_{g in gt} |<n_g, n_nn_pred(g)>|
    nc   = (nc1 + nc2) / 2                           (nc_med: mean of the two medians)
  Normals are Open3D's `estimate_normals()` default: the smallest-eigenvalue
  eigenvector of the covariance of each point's 30 nearest neighbours (itself
  included), sign arbitrary (the absolute dot product ignores it).
- Chamfer: FastVGGT `vggt/utils/eval_utils.py::compute_chamfer_distance`:
  mean_{p} min_g |p - g| + mean_{g} min_p |g - p|, each distance clipped to `max_dist`
  (the ScanNet protocol also voxel-downsamples and subsamples first, see
  `rvggt_jax.eval.protocols`).
- AbsRel: mean over valid pixels of |d_pred - d_ref| / d_ref (the usual monocular
  depth metric; `rvggt eval --against dense` compares a preset's depth with dense's).

Nearest neighbours: `scipy.spatial.cKDTree` (exact Euclidean).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["chamfer_distance", "depth_abs_rel", "estimate_normals", "nearest_distances", "point_cloud_metrics"]

NORMAL_KNN = 30
"""Neighbours per normal (Open3D's KDTreeSearchParamKNN default)."""


def _cloud(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be [N, 3]; got shape {a.shape}")
    if len(a) == 0:
        raise ValueError(f"{name} is empty")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or infinite values (drop invalid points first)")
    return a


def nearest_distances(query, reference) -> tuple[np.ndarray, np.ndarray]:
    """For each query point [N, 3], the distance to and index of its nearest point in
    reference [M, 3] -> (dist [N], idx [N])."""
    dist, idx = cKDTree(reference).query(query, k=1, workers=-1)
    return dist, idx


def estimate_normals(points, knn: int = NORMAL_KNN, chunk: int = 65536) -> np.ndarray:
    """Unit normals [N, 3] of points [N, 3] by PCA over the `knn` nearest neighbours
    (Open3D's default `estimate_normals`); the sign is arbitrary."""
    p = _cloud(points, "points")
    k = min(knn, len(p))
    if k < 3:
        raise ValueError(f"normals need at least 3 points; got {len(p)}")
    tree = cKDTree(p)
    out = np.empty_like(p)
    for s in range(0, len(p), chunk):
        _, idx = tree.query(p[s:s + chunk], k=k, workers=-1)
        nb = p[idx]  # [n, k, 3]
        nb = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb)
        _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
        out[s:s + chunk] = vecs[:, :, 0]
    return out


def point_cloud_metrics(pred_points, gt_points, pred_normals=None, gt_normals=None) -> dict[str, float]:
    """Accuracy, Completeness and Normal Consistency (mean and median) of a predicted
    cloud against ground truth, both already aligned (see the module docstring; CUT3R /
    Spann3R `accuracy` / `completion`, used by RegimeVGGT `eval/eval_7andN.py`).

    pred_points [N, 3], gt_points [M, 3]; pred_normals [N, 3] / gt_normals [M, 3]
    (estimated with `estimate_normals` when None).

    Returns {"acc", "acc_med", "comp", "comp_med", "nc", "nc_med", "nc1", "nc2"}
    (distances in the ground truth's units; NC in [0, 1], 1 = perfect)."""
    pred, gt = _cloud(pred_points, "pred_points"), _cloud(gt_points, "gt_points")
    pn = estimate_normals(pred) if pred_normals is None else np.asarray(pred_normals, np.float64)
    gn = estimate_normals(gt) if gt_normals is None else np.asarray(gt_normals, np.float64)
    if pn.shape != pred.shape or gn.shape != gt.shape:
        raise ValueError(f"normals must match their points: pred {pn.shape} vs {pred.shape}, gt {gn.shape} vs {gt.shape}")
    d_acc, i_acc = nearest_distances(pred, gt)
    d_comp, i_comp = nearest_distances(gt, pred)
    dot1 = np.abs(np.sum(gn[i_acc] * pn, axis=-1))
    dot2 = np.abs(np.sum(gn * pn[i_comp], axis=-1))
    return {
        "acc": float(d_acc.mean()), "acc_med": float(np.median(d_acc)),
        "comp": float(d_comp.mean()), "comp_med": float(np.median(d_comp)),
        "nc": float((dot1.mean() + dot2.mean()) / 2), "nc_med": float((np.median(dot1) + np.median(dot2)) / 2),
        "nc1": float(dot1.mean()), "nc2": float(dot2.mean()),
    }


def chamfer_distance(pred_points, gt_points, max_dist: float | None = None) -> float:
    """Chamfer distance mean_p min_g |p - g| + mean_g min_p |g - p| of two aligned
    clouds pred [N, 3], gt [M, 3], each nearest distance clipped to `max_dist` when given
    (FastVGGT `compute_chamfer_distance`)."""
    pred, gt = _cloud(pred_points, "pred_points"), _cloud(gt_points, "gt_points")
    d1, _ = nearest_distances(pred, gt)
    d2, _ = nearest_distances(gt, pred)
    if max_dist is not None:
        d1, d2 = np.clip(d1, 0, max_dist), np.clip(d2, 0, max_dist)
    return float(d1.mean() + d2.mean())


def depth_abs_rel(pred_depth, ref_depth, valid=None) -> float:
    """mean |pred - ref| / ref over pixels where ref > 0 (and `valid`), depth maps of
    any matching shape (e.g. [S, H, W])."""
    pred, ref = np.asarray(pred_depth, np.float64), np.asarray(ref_depth, np.float64)
    if pred.shape != ref.shape:
        raise ValueError(f"depth maps must have the same shape: {pred.shape} vs {ref.shape}")
    m = (ref > 0) & np.isfinite(ref) & np.isfinite(pred)
    if valid is not None:
        m &= np.asarray(valid, bool)
    if not m.any():
        raise ValueError("no valid reference depth")
    return float(np.mean(np.abs(pred[m] - ref[m]) / ref[m]))
