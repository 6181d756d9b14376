"""Trajectory errors after a Sim(3) alignment: ATE, ARE, RPE-rot, RPE-trans.

Protocol source: FastVGGT `vggt/utils/eval_utils.py::eval_trajectory` (mystorm16/FastVGGT),
run by RegimeVGGT `eval/eval_scannet50.py` for the ScanNet-50 pose table. It calls evo
(`main_ape.ape`, `main_rpe.rpe`) with:

- `align=True, correct_scale=True`: Umeyama Sim(3) of the estimated positions onto the
  reference positions (all poses), applied to the estimated poses;
- ATE = RMSE over frames of |p_est - p_ref| (APE, translation part);
- ARE = RMSE over frames of the angle of R_ref^T R_est in degrees (APE, rotation angle);
- RPE-rot / RPE-trans = RMSE over consecutive pairs (delta = 1 frame, all pairs) of the
  rotation angle (degrees) / translation norm of (Q_i^-1 Q_j)^-1 (P_i^-1 P_j), where Q is
  the reference and P the aligned estimate.

It also passes `align_origin=True`; evo at the time ignored it once `align` was set (evo
1.38 refuses the combination), so it is not applied here.

Which 4x4 matrices are "poses" matters: FastVGGT hands evo the world-to-camera
matrices of both prediction and ground truth (so "positions" are the w2c translations
-R c). `poses="w2c"` reproduces that; the default `poses="c2w"` gives evo
camera-to-world poses, i.e. positions = camera centres, the usual definition of a
trajectory. evo is used as is rather than re-derived, so the numbers are the protocol's.
"""

from __future__ import annotations

from copy import deepcopy

import numpy as np

from rvggt_jax.eval.camera import _inv_se3, as_se3

__all__ = ["trajectory_errors"]


def _trajectory(poses: np.ndarray, stamps: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D

    # evo's PoseTrajectory3D takes 4x4 SE(3) poses directly (quaternion round trips avoided).
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps)


def trajectory_errors(pred_extrinsics, gt_extrinsics, poses: str = "c2w", timestamps=None) -> dict[str, float]:
    """ATE, ARE, RPE-rot, RPE-trans of predicted cameras after Sim(3) alignment (evo).

    pred_extrinsics, gt_extrinsics: [S, 3, 4] world-to-camera, OpenCV, S >= 3 (the
    Umeyama fit needs 3 positions not on one line). poses: "c2w" (evaluate camera
    centres and camera-to-world rotations) or "w2c" (FastVGGT's ScanNet protocol).
    timestamps: [S] (default 0..S-1), only used to pair frames.

    Returns {"ate" (ground-truth units), "are" (deg), "rpe_rot" (deg), "rpe_trans"
    (ground-truth units), "scale" (the Sim(3) scale applied to the prediction)}."""
    import evo.main_ape as main_ape
    import evo.main_rpe as main_rpe
    from evo.core.metrics import PoseRelation, Unit

    if poses not in ("c2w", "w2c"):
        raise ValueError(f"poses must be 'c2w' or 'w2c'; got {poses!r}")
    pred, gt = as_se3(pred_extrinsics, "pred_extrinsics"), as_se3(gt_extrinsics, "gt_extrinsics")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_extrinsics ({len(pred)} cameras) and gt_extrinsics ({len(gt)}) must pair up")
    if len(pred) < 3:
        raise ValueError(f"trajectory errors need at least 3 cameras; got {len(pred)}")
    if poses == "c2w":
        pred, gt = _inv_se3(pred), _inv_se3(gt)
    stamps = np.arange(len(pred), dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    ref, est = _trajectory(gt, stamps), _trajectory(pred, stamps)

    def ape(relation):
        return main_ape.ape(deepcopy(ref), deepcopy(est), relation, align=True, correct_scale=True)

    def rpe(relation):
        return main_rpe.rpe(deepcopy(ref), deepcopy(est), relation, delta=1, delta_unit=Unit.frames,
                            rel_delta_tol=0.01, all_pairs=True, align=True, correct_scale=True)

    ate = ape(PoseRelation.translation_part)
    sim3 = ate.np_arrays["alignment_transformation_sim3"]
    return {
        "ate": float(ate.stats["rmse"]),
        "are": float(ape(PoseRelation.rotation_angle_deg).stats["rmse"]),
        "rpe_rot": float(rpe(PoseRelation.rotation_angle_deg).stats["rmse"]),
        "rpe_trans": float(rpe(PoseRelation.translation_part).stats["rmse"]),
        "scale": float(np.cbrt(abs(np.linalg.det(sim3[:3, :3])))),
    }
