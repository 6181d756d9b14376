"""The evaluation protocols of the paper's tables: frame sampling, what is predicted,
how it is aligned, what is scored (docs/eval.md lists them with their sources).

`PROTOCOLS[dataset]` -> `Protocol`; `protocol.score(scene, pred, infos)` -> metrics.
`pred` holds one scene's model outputs as numpy at network resolution: extrinsics
[S, 3, 4], intrinsics [S, 3, 3], depth [S, H, W], depth_conf [S, H, W], world_points
[S, H, W, 3], world_points_conf [S, H, W]. `infos`: the frames' `ImageInfo`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from rvggt_jax.eval.alignment import (apply_sim3, bbox_scale, icp_point_to_point, median_scale_shift, umeyama,
                                      voxel_downsample)
from rvggt_jax.eval.camera import camera_auc
from rvggt_jax.eval.datasets.files import w2c_to_c2w
from rvggt_jax.eval.network_inputs import gt_points_at_network
from rvggt_jax.eval.points import chamfer_distance, depth_abs_rel, nearest_distances, point_cloud_metrics
from rvggt_jax.eval.trajectory import trajectory_errors

__all__ = ["PROTOCOLS", "SEQUENCE_DATASETS", "Protocol", "against_reference", "pred_points_from_depth",
           "score_trajectory"]

CROP = 224
"""Side of the centre crop (network pixels at width 518) scored by the 7 Scenes / NRGBD
protocol; scaled with the width for other image sizes."""
MAX_RECON_POINTS = 999_999
ICP_THRESHOLD = 0.1
SCANNET_VOXEL, SCANNET_MAX_DIST, SCANNET_MAX_POINTS, SCANNET_SEED = 0.05, 0.5, 100_000, 33


@dataclasses.dataclass(frozen=True)
class Protocol:
    """How one dataset is evaluated. `stride` / `frames` / `sampling`: the default frame
    selection (`sample_indices`); `metrics`: the table's columns, `headline` first."""

    dataset: str
    metrics: tuple[str, ...]
    score: Callable
    stride: int = 1
    frames: int | None = None
    sampling: str = "first"
    higher_is_better: tuple[str, ...] = ()
    source: str = ""
    stride_cap_half: bool = False  # NRGBD's loader: stride = min(K, n // 2)
    sequence: bool = False  # a long trajectory: may be predicted in chunks (--chunk-frames)

    @property
    def headline(self) -> str:
        return self.metrics[0]


def _rng_subsample(p: np.ndarray, n: int, rng) -> np.ndarray:
    return p if len(p) <= n else p[rng.choice(len(p), n, replace=False)]


def pred_points_from_depth(pred: dict, conf_threshold: float | None = None) -> np.ndarray:
    """World points [N, 3] (float32) of the predicted depth unprojected with the
    predicted cameras; pixels with depth_conf < conf_threshold dropped."""
    from rvggt_jax.geometry import unproject_depth_map_to_point_map

    pts = unproject_depth_map_to_point_map(pred["depth"], pred["extrinsics"], pred["intrinsics"])
    keep = np.isfinite(pts).all(-1)
    if conf_threshold is not None:
        keep &= pred["depth_conf"] >= conf_threshold
    return pts[keep]


# ---------------------------------------------------------------------------------------
# 7 Scenes / NRGBD: Acc / Comp / NC of the point-map head
# ---------------------------------------------------------------------------------------


def score_dense_recon(scene, pred: dict, infos) -> dict[str, float]:
    """CUT3R / RegimeVGGT `eval_7andN.py`: ground-truth points of every view in the
    first camera's frame vs the point-map head's points (no confidence filter);
    `median_scale_shift` on all valid pixels; the central 224x224 crop of each view;
    at most 999,999 points each (seeded subsample); point-to-point ICP (threshold 0.1);
    then `point_cloud_metrics` with estimated normals."""
    s, h, w = pred["depth"].shape
    c = max(1, round(CROP * w / 518)) // 2
    crop = np.zeros((h, w), bool)
    crop[max(h // 2 - c, 0):h // 2 + c, max(w // 2 - c, 0):w // 2 + c] = True
    e0 = scene.extrinsics[0]
    gts, prs, in_crop = [], [], []
    for i in range(s):  # valid pixels only: no full-size float64 copies of long sequences
        world, valid = gt_points_at_network(scene, i, infos[i], (h, w))
        valid &= np.isfinite(pred["world_points"][i]).all(-1)
        gts.append(world[valid] @ e0[:, :3].T + e0[:, 3])  # the protocol's ground truth is in camera 1
        prs.append(pred["world_points"][i][valid])
        in_crop.append(crop[valid])
    gt, pr, in_crop = np.concatenate(gts), np.concatenate(prs), np.concatenate(in_crop)
    if len(gt) < 10:
        raise ValueError(f"scene {scene.name}: fewer than 10 pixels with ground-truth depth")
    pr, gt = median_scale_shift(pr, gt)
    pr, gt = pr[in_crop], gt[in_crop]
    if len(gt) < 10:
        raise ValueError(f"scene {scene.name}: fewer than 10 pixels with ground-truth depth in the central crop")
    rng = np.random.default_rng(0)
    pr, gt = _rng_subsample(pr, MAX_RECON_POINTS, rng), _rng_subsample(gt, MAX_RECON_POINTS, rng)
    t = icp_point_to_point(pr, gt, ICP_THRESHOLD)
    pr = pr @ t[:3, :3].T + t[:3, 3]
    return point_cloud_metrics(pr, gt)


# ---------------------------------------------------------------------------------------
# ScanNet-50: Chamfer + trajectory
# ---------------------------------------------------------------------------------------


def score_scannet(scene, pred: dict, infos) -> dict[str, float]:
    """FastVGGT `eval_utils.py` (RegimeVGGT `eval_scannet50.py`): points from the depth
    head and the predicted cameras (depth_conf >= 1), moved into the ground-truth world
    with the first frame's pose, aligned by `bbox_scale`, voxel-downsampled (0.05) after
    a seeded subsample to 100k, Chamfer with distances clipped at 0.5; trajectory errors
    of the world-to-camera matrices (`poses="w2c"`) against the ground truth expressed
    relative to the first frame."""
    out: dict[str, float] = {}
    gt_c2w = w2c_to_c2w(scene.extrinsics)
    first = gt_c2w[0]
    if scene.points_path is not None:
        pts = pred_points_from_depth(pred, conf_threshold=1.0)
        gt = scene.gt_points()
        # The protocol aligns all points, then subsamples; both steps commute (the
        # alignment is affine), so the bounding boxes come from all points and only the
        # subsample is converted and moved.
        r0, t0 = first[:3, :3].astype(np.float32), first[:3, 3].astype(np.float32)
        lo, hi = None, None
        for chunk in np.array_split(pts, max(1, len(pts) // 5_000_000)):
            moved = chunk @ r0.T + t0
            lo = moved.min(0) if lo is None else np.minimum(lo, moved.min(0))
            hi = moved.max(0) if hi is None else np.maximum(hi, moved.max(0))

        def subsample(p):
            rng = np.random.RandomState(SCANNET_SEED)  # FastVGGT reseeds before each cloud
            return p if len(p) <= SCANNET_MAX_POINTS else p[rng.choice(len(p), SCANNET_MAX_POINTS, replace=False)]

        pts = subsample(pts).astype(np.float64) @ first[:3, :3].T + first[:3, 3]
        pts, scale = bbox_scale(pts, gt, pred_bounds=(lo.astype(np.float64), hi.astype(np.float64)))
        gt = subsample(gt)
        pts, gt = voxel_downsample(pts, SCANNET_VOXEL), voxel_downsample(gt, SCANNET_VOXEL)
        out["chamfer"] = chamfer_distance(pts, gt, max_dist=SCANNET_MAX_DIST)
        out["scale"] = scale
    rel_c2w = np.linalg.inv(first)[None] @ gt_c2w
    gt_w2c = np.linalg.inv(rel_c2w)[:, :3]
    if len(scene) >= 3:
        traj = trajectory_errors(pred["extrinsics"], gt_w2c, poses="w2c")
        out.update({k: traj[k] for k in ("ate", "are", "rpe_rot", "rpe_trans")})
    return out


# ---------------------------------------------------------------------------------------
# Tanks and Temples / DTU: AUC of relative poses
# ---------------------------------------------------------------------------------------


def score_pose_auc(scene, pred: dict, infos) -> dict[str, float]:
    """Upstream VGGT `test_co3d.py` / RegimeVGGT `eval_pose_tnt.py`: `camera_auc` at 30,
    15, 5 degrees over all frame pairs."""
    r = camera_auc(pred["extrinsics"], scene.extrinsics, thresholds=(30, 15, 5))
    return {k: v for k, v in r.items() if k != "pairs"}


# ---------------------------------------------------------------------------------------
# generic folder: whatever ground truth there is
# ---------------------------------------------------------------------------------------


def score_folder(scene, pred: dict, infos) -> dict[str, float]:
    """Cameras: `camera_auc` (30/15/5/3) and, with >= 3 frames, `trajectory_errors`
    (camera centres). With depth maps: AbsRel of the predicted depth after one median
    scale per scene, and Chamfer / Acc / Comp of the depth-head points after a Sim(3)
    (Umeyama on the camera centres) against the ground-truth cloud (points.ply, else
    the unprojected depth maps), 100k points each (seeded)."""
    out = {k: v for k, v in camera_auc(pred["extrinsics"], scene.extrinsics, (30, 15, 5, 3)).items() if k != "pairs"}
    if len(scene) >= 3:
        out.update(trajectory_errors(pred["extrinsics"], scene.extrinsics))
    s, h, w = pred["depth"].shape
    gt_cloud = None
    if scene.has_depth:
        gts = [gt_points_at_network(scene, i, infos[i], (h, w)) for i in range(s)]
        gt_depth = np.stack([(p @ scene.extrinsics[i][:, :3].T + scene.extrinsics[i][:, 3])[..., 2] * v
                             for i, (p, v) in enumerate(gts)])
        valid = np.stack([v for _, v in gts])
        ratio = np.median(gt_depth[valid]) / np.median(pred["depth"][valid])
        out["abs_rel"] = depth_abs_rel(pred["depth"] * ratio, gt_depth, valid)
        gt_cloud = np.concatenate([p[v] for p, v in gts])
    if scene.points_path is not None:
        gt_cloud = scene.gt_points()
    if gt_cloud is not None and len(scene) >= 3:
        centers = lambda e: w2c_to_c2w(e)[:, :3, 3]  # noqa: E731
        sc, r, t = umeyama(centers(pred["extrinsics"]), centers(scene.extrinsics))
        rng = np.random.default_rng(0)
        pts = apply_sim3(_rng_subsample(pred_points_from_depth(pred), 100_000, rng), sc, r, t)
        gt_cloud = _rng_subsample(gt_cloud, 100_000, rng)
        acc, comp = nearest_distances(pts, gt_cloud)[0].mean(), nearest_distances(gt_cloud, pts)[0].mean()
        out.update(chamfer=float(acc + comp), acc=float(acc), comp=float(comp))
    return out


# ---------------------------------------------------------------------------------------
# long sequences (KITTI odometry, TUM RGB-D): trajectory errors
# ---------------------------------------------------------------------------------------


def score_trajectory(scene, pred: dict, infos=None) -> dict[str, float]:
    """`trajectory_errors` on camera centres (`poses="c2w"`): ATE, ARE, RPE-trans,
    RPE-rot (consecutive frames) after the Sim(3) (evo Umeyama, scale included: a
    monocular prediction has no metric scale) that best fits the predicted centres onto
    the ground truth; `scale` is that fit's scale. pred["extrinsics"] [S, 3, 4], in any
    frame and scale (one forward's, or a chunked run's first chunk's). Needs S >= 3."""
    if len(scene) < 3:
        raise ValueError(f"scene {scene.name}: trajectory errors need at least 3 frames; got {len(scene)}")
    return trajectory_errors(pred["extrinsics"], scene.extrinsics, poses="c2w")


def against_reference(pred: dict, ref: dict) -> dict[str, float]:
    """How far one preset's outputs are from a reference run's (dense) on the same
    frames, without ground truth: camera AUC / RRA / RTA (30/15/5/3) with the reference
    cameras as truth; depth AbsRel against the reference depth (same scale, no
    alignment); Chamfer between the depth-head clouds after a Sim(3) (Umeyama on camera
    centres; none with fewer than 3 frames), 100k points each (seeded)."""
    out = {}
    if len(pred["extrinsics"]) >= 2:
        out.update({k: v for k, v in camera_auc(pred["extrinsics"], ref["extrinsics"], (30, 15, 5, 3)).items()
                    if k != "pairs"})
    out["abs_rel"] = depth_abs_rel(pred["depth"], ref["depth"])
    rng = np.random.default_rng(0)
    a = _rng_subsample(pred_points_from_depth(pred), 100_000, rng).astype(np.float64)
    b = _rng_subsample(pred_points_from_depth(ref), 100_000, rng)
    if len(pred["extrinsics"]) >= 3:
        centers = lambda e: w2c_to_c2w(e)[:, :3, 3]  # noqa: E731
        try:
            a = apply_sim3(a, *umeyama(centers(pred["extrinsics"]), centers(ref["extrinsics"])))
        except ValueError:  # degenerate (coincident) cameras: compare as predicted
            pass
    out["chamfer"] = chamfer_distance(a, b)
    return out


_TRAJ_METRICS = ("ate", "rpe_trans", "rpe_rot", "are")
_SRC_TRAJ = "evo APE / RPE on camera centres after a Sim(3) alignment"
_SRC_7N = "RegimeVGGT eval/eval_7andN.py (CUT3R criterion + accuracy/completion)"
PROTOCOLS: dict[str, Protocol] = {
    "7scenes": Protocol("7scenes", ("acc", "acc_med", "comp", "comp_med", "nc", "nc_med"), score_dense_recon,
                        stride=10, higher_is_better=("nc", "nc_med"), source=_SRC_7N),
    "nrgbd": Protocol("nrgbd", ("acc", "acc_med", "comp", "comp_med", "nc", "nc_med"), score_dense_recon,
                      stride=10, higher_is_better=("nc", "nc_med"), source=_SRC_7N, stride_cap_half=True),
    "scannet": Protocol("scannet", ("chamfer", "ate", "are", "rpe_rot", "rpe_trans"), score_scannet,
                        frames=1000, sampling="scannet",
                        source="RegimeVGGT eval/eval_scannet50.py + FastVGGT vggt/utils/eval_utils.py"),
    "tnt": Protocol("tnt", ("auc@30", "auc@15", "auc@5"), score_pose_auc, higher_is_better=("auc@30", "auc@15", "auc@5"),
                    source="RegimeVGGT eval/eval_pose_tnt.py + VGGT evaluation/test_co3d.py"),
    "dtu": Protocol("dtu", ("auc@30", "auc@15", "auc@5"), score_pose_auc, frames=48,
                    higher_is_better=("auc@30", "auc@15", "auc@5"), source="VGGT evaluation/test_co3d.py"),
    "folder": Protocol("folder", ("auc@30", "auc@15", "auc@5", "auc@3", "ate", "are", "rpe_rot", "rpe_trans",
                                  "abs_rel", "chamfer"), score_folder,
                       higher_is_better=("auc@30", "auc@15", "auc@5", "auc@3"), source="this project"),
    "kitti": Protocol("kitti", _TRAJ_METRICS, score_trajectory, sequence=True, source=_SRC_TRAJ),
    "tum": Protocol("tum", _TRAJ_METRICS, score_trajectory, sequence=True, source=_SRC_TRAJ),
}
SEQUENCE_DATASETS = tuple(name for name, p in PROTOCOLS.items() if p.sequence)

AGAINST_METRICS = ("auc@30", "auc@15", "auc@5", "auc@3", "abs_rel", "chamfer")
AGAINST_HIGHER = ("auc@30", "auc@15", "auc@5", "auc@3")
