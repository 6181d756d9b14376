"""A trained model scored on held-out procedural scenes, against the trivial baselines.

    scene = make_scene(frames=8, height=84, width=112, seed=3)   # a held-out seed
    out = rvggt_forward(params, images_of(scene), config)
    s = score_scene(out, scene)

`score_scene` gives, for one scene (all numbers per scene; `summarize` takes medians
over scenes):

- `rot_err_median`: the median over frame pairs of the relative rotation error
  (degrees), and `rot_err_identity`: the same for cameras all predicted as the first
  one (identity rotations): a model that learned nothing about cameras scores near it.
- `auc@30`, `rra@15`, `rta@15`: `rvggt_jax.eval.camera.camera_auc`.
- `abs_rel`: depth AbsRel with each predicted depth map scaled by the ratio of medians
  (ground truth over prediction, over the valid pixels), and `abs_rel_constant`: the
  AbsRel of the best constant depth per image (the weighted median of the true depths
  with weights 1 / depth minimises mean |c - d| / d): a model that learned no structure
  scores near it.
- `chamfer`: the Chamfer distance (`rvggt_jax.eval.points.chamfer_distance`: the sum
  of the two directions' mean nearest distances) between the predicted point
  map and the true points of the valid pixels, after a Sim(3) (Umeyama) on the
  pixel-wise pairs, in units of the true scene's scale (mean distance to the centroid).

Used by `rvggt demo` (on its bundled scene), the shipped model's tests, and
`benchmarks/bench_trade.py` (the speed-quality table of docs/eval.md).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from rvggt_jax.eval.alignment import apply_sim3, umeyama
from rvggt_jax.eval.camera import camera_auc, relative_pose_errors
from rvggt_jax.eval.points import chamfer_distance

__all__ = ["best_constant_abs_rel", "camera_scores", "images_of", "predicted_cameras", "score_scene", "summarize"]


def images_of(scene) -> np.ndarray:
    """The network input [1, S, 3, H, W] float32 in [0, 1] of a `SyntheticScene` rendered
    at the network size."""
    return (scene.images.astype(np.float32) / np.float32(255.0)).transpose(0, 3, 1, 2)[None]


def predicted_cameras(out: dict, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(extrinsics [S, 3, 4], intrinsics [S, 3, 3]) of the first batch element's pose
    encoding."""
    from rvggt_jax.geometry import pose_encoding_to_extri_intri

    ext, intr = pose_encoding_to_extri_intri(out["pose_enc"], hw)
    return np.asarray(ext[0], np.float64), np.asarray(intr[0], np.float64)


def best_constant_abs_rel(depth: np.ndarray, valid: np.ndarray) -> float:
    """Mean over images of the AbsRel of the best constant depth of each image
    (depth [S, H, W], valid [S, H, W])."""
    vals = []
    for d, m in zip(depth, valid):
        x = np.sort(d[m].astype(np.float64))
        if x.size == 0:
            continue
        w = 1.0 / x
        c = x[np.searchsorted(np.cumsum(w), 0.5 * w.sum())]
        vals.append(float(np.mean(np.abs(c - x) / x)))
    return float(np.mean(vals))


def _abs_rel_median_scaled(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> float:
    vals = []
    for p, g, m in zip(pred, gt, valid):
        if not m.any():
            continue
        p, g = p[m].astype(np.float64), g[m].astype(np.float64)
        p = p * (np.median(g) / max(np.median(p), 1e-12))
        vals.append(float(np.mean(np.abs(p - g) / g)))
    return float(np.mean(vals))


def camera_scores(pred_extrinsics: np.ndarray, gt_extrinsics: np.ndarray) -> dict[str, float]:
    """Predicted cameras [S, 3, 4] against the true ones [S, 3, 4] (world-to-camera):
    median relative rotation error (degrees), the same for identity rotations (every
    camera the first), AUC@30, RRA@15 and RTA@15."""
    gt = np.asarray(gt_extrinsics, np.float64)
    r_err, _ = relative_pose_errors(pred_extrinsics, gt)
    r_id, _ = relative_pose_errors(np.repeat(gt[:1], len(gt), axis=0), gt)
    cams = camera_auc(pred_extrinsics, gt, thresholds=(30, 15))
    return {"rot_err_median": float(np.median(r_err)), "rot_err_identity": float(np.median(r_id)),
            "auc@30": cams["auc@30"], "rra@15": cams["rra@15"], "rta@15": cams["rta@15"]}


def score_scene(out: dict, scene, max_points: int = 20000, seed: int = 0) -> dict[str, float]:
    """The metrics of the module docstring for a forward's outputs `out` (batch of one)
    on `scene` (a `SyntheticScene` at the network size)."""
    _, h, w = scene.depth.shape
    ext, _ = predicted_cameras(out, (h, w))
    valid = scene.valid
    depth = np.asarray(out["depth"][0, ..., 0], np.float64)
    res = {**camera_scores(ext, scene.extrinsics),
           "abs_rel": _abs_rel_median_scaled(depth, scene.depth, valid),
           "abs_rel_constant": best_constant_abs_rel(scene.depth, valid)}
    pts = np.asarray(out["world_points"][0], np.float64)[valid]
    gt = scene.points[valid].astype(np.float64)
    ok = np.isfinite(pts).all(axis=1)
    pts, gt = pts[ok], gt[ok]
    if len(gt) >= 3:
        sc, r, t = umeyama(pts, gt)
        aligned = apply_sim3(pts, sc, r, t)
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(gt), min(max_points, len(gt)), replace=False)
        scale = float(np.mean(np.linalg.norm(gt - gt.mean(axis=0), axis=1)))
        res["chamfer"] = chamfer_distance(aligned[pick], gt[pick]) / scale
    else:
        res["chamfer"] = float("nan")
    return res


def summarize(rows: Iterable[dict[str, float]]) -> dict[str, float]:
    """Median over scenes of each metric."""
    rows = list(rows)
    return {k: float(np.nanmedian([r[k] for r in rows])) for k in rows[0]}
