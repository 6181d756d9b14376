"""Camera pose accuracy from pairwise relative poses: RRA, RTA and AUC.

Protocol source: upstream VGGT's `evaluation/test_co3d.py` (facebookresearch/vggt,
evaluation branch), the same functions RegimeVGGT's `eval/eval_pose_tnt.py` uses for
Tanks & Temples and DTU:

- for every unordered pair i < j (S (S - 1) / 2 pairs), the relative pose
  E_i E_j^-1 of the prediction and of the ground truth (world-to-camera);
- rotation error: the angle of R_gt^T R_pred, computed from quaternions as
  arccos(1 - 2 (1 - <q_pred, q_gt>^2)) (with 1 - <.,.>^2 clamped to >= 1e-15);
- translation error: the angle between the two relative translations, direction
  only, sign-ambiguous: min(theta, 180 - theta) (a zero translation counts as 90 deg);
- RRA@tau / RTA@tau: the fraction of pairs whose rotation / translation error is
  below tau degrees;
- AUC@T: the max of the two errors per pair, histogrammed in 1-degree bins on
  [0, T]; the mean of the cumulative histogram (normalised by the number of pairs), i.e.
  (1/T) sum_{k=1..T} fraction(err < k) (the last bin is closed).

Every metric is invariant to a similarity transform of either set of cameras.
"""

from __future__ import annotations

import numpy as np

__all__ = ["as_se3", "camera_auc", "relative_pose_errors", "rotation_angle_deg", "translation_angle_deg"]


def as_se3(extrinsics, name: str = "extrinsics") -> np.ndarray:
    """[S, 3, 4] or [S, 4, 4] world-to-camera -> [S, 4, 4] float64."""
    e = np.asarray(extrinsics, dtype=np.float64)
    if e.ndim != 3 or e.shape[1:] not in ((3, 4), (4, 4)):
        raise ValueError(f"{name} must be [S, 3, 4] (or [S, 4, 4]) world-to-camera matrices; got shape {e.shape}")
    if not np.isfinite(e).all():
        raise ValueError(f"{name} contain NaN or infinite values")
    out = np.tile(np.eye(4), (len(e), 1, 1))
    out[:, :3, :] = e[:, :3, :]
    return out


def _inv_se3(e: np.ndarray) -> np.ndarray:
    r_t = np.swapaxes(e[..., :3, :3], -1, -2)
    out = np.tile(np.eye(4), e.shape[:-2] + (1, 1))
    out[..., :3, :3] = r_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", r_t, e[..., :3, 3])
    return out


def _quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions [..., 4] of rotation matrices [..., 3, 3] (sign irrelevant here)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat().reshape(r.shape[:-2] + (4,))


def rotation_angle_deg(r_gt: np.ndarray, r_pred: np.ndarray, eps: float = 1e-15) -> np.ndarray:
    """Angle (degrees) of R_gt^T R_pred for rotations [..., 3, 3], computed as
    upstream from quaternions: arccos(1 - 2 max(1 - <q_gt, q_pred>^2, eps))."""
    dot = np.sum(_quat(r_gt) * _quat(r_pred), axis=-1)
    loss = np.maximum(1.0 - dot ** 2, eps)
    return np.degrees(np.arccos(np.clip(1.0 - 2.0 * loss, -1.0, 1.0)))


def translation_angle_deg(t_gt: np.ndarray, t_pred: np.ndarray, eps: float = 1e-15) -> np.ndarray:
    """Sign-ambiguous angle (degrees, in [0, 90]) between translations [..., 3]:
    arccos(sqrt(1 - max(1 - <t_gt/|t_gt|, t_pred/|t_pred|>^2, eps))), as upstream;
    non-finite results count as 1e6 degrees."""
    a = t_gt / (np.linalg.norm(t_gt, axis=-1, keepdims=True) + eps)
    b = t_pred / (np.linalg.norm(t_pred, axis=-1, keepdims=True) + eps)
    loss = np.maximum(1.0 - np.sum(a * b, axis=-1) ** 2, eps)
    with np.errstate(invalid="ignore"):
        err = np.degrees(np.arccos(np.sqrt(1.0 - loss)))
    err = np.where(np.isfinite(err), err, 1e6)
    return np.minimum(err, np.abs(180.0 - err))


def relative_pose_errors(pred_extrinsics, gt_extrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation angle errors (degrees) of all S (S - 1) / 2 pairs i < j,
    ordered as `itertools.combinations(range(S), 2)`.

    pred_extrinsics, gt_extrinsics: [S, 3, 4] world-to-camera (OpenCV). Returns
    (r_err [P], t_err [P])."""
    pred, gt = as_se3(pred_extrinsics, "pred_extrinsics"), as_se3(gt_extrinsics, "gt_extrinsics")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_extrinsics ({len(pred)} cameras) and gt_extrinsics ({len(gt)}) must pair up")
    if len(pred) < 2:
        raise ValueError(f"relative pose errors need at least 2 cameras; got {len(pred)}")
    i1, i2 = np.triu_indices(len(pred), k=1)
    rel_gt = gt[i1] @ _inv_se3(gt[i2])
    rel_pred = pred[i1] @ _inv_se3(pred[i2])
    r_err = rotation_angle_deg(rel_gt[:, :3, :3], rel_pred[:, :3, :3])
    t_err = translation_angle_deg(rel_gt[:, :3, 3], rel_pred[:, :3, 3])
    return r_err, t_err


def auc_from_errors(r_err: np.ndarray, t_err: np.ndarray, max_threshold: int) -> float:
    """AUC@max_threshold of per-pair errors (degrees): mean of the cumulative 1-degree
    histogram of max(r_err, t_err) on [0, max_threshold]."""
    m = np.maximum(r_err, t_err)
    hist, _ = np.histogram(m, bins=np.arange(int(max_threshold) + 1))
    return float(np.mean(np.cumsum(hist.astype(np.float64) / len(m))))


def camera_auc(pred_extrinsics, gt_extrinsics, thresholds=(30, 15, 5, 3)) -> dict[str, float]:
    """RRA, RTA and AUC of predicted cameras against ground truth (see the module
    docstring for the formulas; upstream VGGT `evaluation/test_co3d.py`).

    pred_extrinsics, gt_extrinsics: [S, 3, 4] world-to-camera, OpenCV, S >= 2; any
    world frame and scale (the metrics use relative poses and translation directions).
    thresholds: integer degrees.

    Returns {"auc@T", "rra@T", "rta@T" for each T} as fractions in [0, 1], plus
    "pairs" (the number of pairs)."""
    r_err, t_err = relative_pose_errors(pred_extrinsics, gt_extrinsics)
    out: dict[str, float] = {}
    for t in thresholds:
        if int(t) != t or t <= 0:
            raise ValueError(f"thresholds must be positive whole degrees; got {t}")
        t = int(t)
        out[f"auc@{t}"] = auc_from_errors(r_err, t_err, t)
        out[f"rra@{t}"] = float(np.mean(r_err < t))
        out[f"rta@{t}"] = float(np.mean(t_err < t))
    out["pairs"] = float(len(r_err))
    return out
