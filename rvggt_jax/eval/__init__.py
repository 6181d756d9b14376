"""Evaluation: the metrics of the paper's tables, dataset readers and `rvggt eval`.

NumPy in, floats out; extrinsics are world-to-camera `[S, 3, 4]` (OpenCV), points `[N, 3]`.

    camera_auc(pred_extrinsics, gt_extrinsics, thresholds=(30, 15, 5, 3))  # auc@T, rra@T, rta@T
    trajectory_errors(pred_extrinsics, gt_extrinsics)                       # ate, are, rpe_rot, rpe_trans
    point_cloud_metrics(pred_points, gt_points)                             # acc, comp, nc (+ medians)
    chamfer_distance(pred_points, gt_points)
    umeyama(src, dst) -> (s, R, t)                                          # Sim(3) alignment

Protocols (frame sampling, alignment, which head is scored): `rvggt_jax.eval.protocols`
and docs/eval.md. Readers: `rvggt_jax.eval.datasets`.
"""

import importlib

# Resolved on first use: `rvggt --help` imports this package (for the `eval` options)
# and must not need scipy / evo, which only the metrics use (the `eval` extra).
_LAZY = {
    "apply_sim3": "alignment", "bbox_scale": "alignment", "icp_point_to_point": "alignment",
    "median_scale_shift": "alignment", "umeyama": "alignment", "voxel_downsample": "alignment",
    "camera_auc": "camera", "relative_pose_errors": "camera",
    "chamfer_distance": "points", "depth_abs_rel": "points", "estimate_normals": "points",
    "point_cloud_metrics": "points",
    "trajectory_errors": "trajectory",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"rvggt_jax.eval.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'rvggt_jax.eval' has no attribute {name!r}")
