"""The evaluation metrics on exact truth: ground truth scored as a prediction is perfect,
known perturbations give the analytically expected values, alignment undoes a known
Sim(3)."""

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rvggt_jax.eval import (apply_sim3, camera_auc, chamfer_distance, depth_abs_rel, icp_point_to_point,
                            median_scale_shift, point_cloud_metrics, relative_pose_errors, trajectory_errors, umeyama,
                            voxel_downsample)
from rvggt_jax.synthetic import make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=6, height=42, width=56, seed=7)


def random_sim3(seed=0):
    rng = np.random.default_rng(seed)
    return float(rng.uniform(0.3, 3.0)), Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3)


def transform_cameras(w2c, s, r, t):
    """The same cameras after the world moves by x -> s R x + t (w2c [S, 3, 4])."""
    rot = w2c[:, :, :3] @ r.T
    centers = -np.einsum("sji,sj->si", w2c[:, :, :3], w2c[:, :, 3])
    new_c = s * centers @ r.T + t
    return np.concatenate([rot, -np.einsum("sij,sj->si", rot, new_c)[..., None]], axis=-1)


def rotate_camera(w2c, i, deg, axis=(0.0, 1.0, 0.0)):
    """Turn camera i by `deg` degrees about its own centre (axis in camera coordinates)."""
    q = Rotation.from_rotvec(np.deg2rad(deg) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    out = w2c.copy()
    out[i, :, :3] = q @ w2c[i, :, :3]
    out[i, :, 3] = q @ w2c[i, :, 3]  # t = -R c with the centre c unchanged
    return out, q


# --------------------------------------------------------------------------- cameras


def test_camera_auc_perfect_and_similarity_invariant(scene):
    gt = scene.extrinsics
    for pred in (gt, transform_cameras(gt, *random_sim3(1))):
        r = camera_auc(pred, gt)
        for t in (30, 15, 5, 3):
            assert r[f"auc@{t}"] == pytest.approx(1.0) and r[f"rra@{t}"] == 1.0 and r[f"rta@{t}"] == 1.0
        assert r["pairs"] == 15


def test_camera_auc_five_degrees_on_one_camera(scene):
    gt = scene.extrinsics
    s = len(gt)
    pred, q = rotate_camera(gt, 0, 5.0)
    r_err, t_err = relative_pose_errors(pred, gt)
    pairs = list(itertools.combinations(range(s), 2))
    involved = np.array([0 in p for p in pairs])
    np.testing.assert_allclose(r_err[involved], 5.0, atol=1e-6)
    np.testing.assert_allclose(r_err[~involved], 0.0, atol=1e-5)
    # pairs (0, j): the relative translation turns by q; the angle between t and q t
    inv = lambda e: np.linalg.inv(np.vstack([e, [0, 0, 0, 1]]))  # noqa: E731
    for k, (i, j) in enumerate(pairs):
        if i == 0:
            t_rel = (np.vstack([gt[0], [0, 0, 0, 1]]) @ inv(gt[j]))[:3, 3]
            cos = abs(t_rel @ (q @ t_rel)) / np.dot(t_rel, t_rel)
            assert t_err[k] == pytest.approx(np.degrees(np.arccos(min(cos, 1.0))), abs=1e-5)
    assert (t_err <= 5.0 + 1e-6).all()
    m, p = s - 1, len(pairs)
    r = camera_auc(pred, gt, thresholds=(3, 15))
    assert r["rra@3"] == pytest.approx(1 - m / p) and r["rra@15"] == 1.0 and r["auc@3"] == pytest.approx(1 - m / p)
    # 5.5 degrees (5.0 sits on a bin edge): every perturbed pair's max error is in [5, 6),
    # so it counts from the 6-degree step of the cumulative histogram on
    pred, _ = rotate_camera(gt, 0, 5.5)
    r = camera_auc(pred, gt, thresholds=(30, 15))
    assert r["auc@30"] == pytest.approx((5 * (1 - m / p) + 25) / 30)
    assert r["auc@15"] == pytest.approx((5 * (1 - m / p) + 10) / 15)


def test_camera_metrics_reject_bad_input(scene):
    with pytest.raises(ValueError, match=r"\[S, 3, 4\]"):
        camera_auc(scene.extrinsics[:, :2], scene.extrinsics)
    with pytest.raises(ValueError, match="pair up"):
        camera_auc(scene.extrinsics[:3], scene.extrinsics)
    with pytest.raises(ValueError, match="NaN"):
        camera_auc(np.full_like(scene.extrinsics, np.nan), scene.extrinsics)


# --------------------------------------------------------------------------- trajectory


@pytest.mark.parametrize("poses", ["c2w", "w2c"])
def test_trajectory_perfect(scene, poses):
    r = trajectory_errors(scene.extrinsics, scene.extrinsics, poses=poses)
    for k in ("ate", "are", "rpe_rot", "rpe_trans"):
        assert r[k] == pytest.approx(0.0, abs=1e-6), k
    assert r["scale"] == pytest.approx(1.0)


def test_trajectory_undoes_a_similarity(scene):
    s, r, t = random_sim3(3)
    pred = transform_cameras(scene.extrinsics, s, r, t)
    out = trajectory_errors(pred, scene.extrinsics)
    for k in ("ate", "are", "rpe_rot", "rpe_trans"):
        assert out[k] == pytest.approx(0.0, abs=1e-6), k
    assert out["scale"] == pytest.approx(1 / s)


def test_trajectory_five_degrees_on_one_camera(scene):
    gt = scene.extrinsics
    n, k = len(gt), 2
    pred, q = rotate_camera(gt, k, 5.0, axis=(1.0, 0.5, 0.0))
    out = trajectory_errors(pred, gt)
    # centres are unchanged: the alignment is the identity, positions are exact
    assert out["ate"] == pytest.approx(0.0, abs=1e-9)
    assert out["are"] == pytest.approx(np.sqrt(25.0 / n), rel=1e-6)
    assert out["rpe_rot"] == pytest.approx(np.sqrt(2 * 25.0 / (n - 1)), rel=1e-6)
    # only the pair (k, k+1) sees a translation error: |R_k'^T d - R_k^T d|, d = c_{k+1} - c_k
    c = -np.einsum("sji,sj->si", gt[:, :, :3], gt[:, :, 3])
    d = c[k + 1] - c[k]
    err = np.linalg.norm(pred[k, :, :3] @ d - gt[k, :, :3] @ d)
    assert out["rpe_trans"] == pytest.approx(np.sqrt(err ** 2 / (n - 1)), rel=1e-6)


# --------------------------------------------------------------------------- alignment


def test_umeyama_undoes_a_known_sim3(scene):
    pts, _ = scene.cloud()
    s, r, t = random_sim3(5)
    moved = apply_sim3(pts, s, r, t)
    s2, r2, t2 = umeyama(pts, moved)
    assert s2 == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(r2, r, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-8)
    np.testing.assert_allclose(apply_sim3(moved, *umeyama(moved, pts)), pts, atol=1e-8)
    s3, r3, _ = umeyama(pts, moved, with_scale=False)
    assert s3 == 1.0 and np.allclose(r3, r, atol=1e-6)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(pts[:2], moved[:2])


def test_icp_recovers_a_small_rigid_motion(scene):
    pts, _ = scene.cloud()
    r = Rotation.from_euler("xyz", [2.0, -1.5, 1.0], degrees=True).as_matrix()
    moved = pts @ r.T + np.array([0.02, -0.01, 0.015])
    t = icp_point_to_point(moved, pts, threshold=0.1, max_iter=60)
    back = moved @ t[:3, :3].T + t[:3, 3]
    assert np.sqrt(np.mean(np.sum((back - pts) ** 2, axis=1))) < 1e-3


def test_median_scale_shift_undoes_scale_and_depth_shift(scene):
    gt = scene.points[0][scene.valid[0]].astype(np.float64)
    pred = gt * 2.5 + np.array([0.0, 0.0, 4.0])
    p2, g2 = median_scale_shift(pred, gt)
    np.testing.assert_allclose(p2, g2, atol=1e-9)


def test_voxel_downsample_means():
    pts = np.array([[0.0, 0, 0], [0.2, 0, 0], [1.0, 1, 1], [1.1, 1, 1]])
    out = voxel_downsample(pts, 0.5)
    np.testing.assert_allclose(out, [[0.1, 0, 0], [1.05, 1, 1]])


# --------------------------------------------------------------------------- points


def grid_plane(step, half=1.0):
    """A dense square grid on the plane z = 0: [N, 3]."""
    a = np.arange(-half, half + step / 2, step)
    x, y = np.meshgrid(a, a)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def test_point_metrics_perfect(scene):
    pts, _ = scene.cloud()
    r = point_cloud_metrics(pts, pts)
    assert r["acc"] == r["comp"] == r["acc_med"] == r["comp_med"] == 0.0
    assert r["nc"] == pytest.approx(1.0) and r["nc_med"] == pytest.approx(1.0)
    assert chamfer_distance(pts, pts) == 0.0


def test_point_metrics_similarity_removed_by_alignment(scene):
    pts, nrm = scene.cloud()
    s, r, t = random_sim3(9)
    pred = apply_sim3(pts, s, r, t)
    assert chamfer_distance(pred, pts) > 0.1
    aligned = apply_sim3(pred, *umeyama(pred, pts))
    assert chamfer_distance(aligned, pts) == pytest.approx(0.0, abs=1e-8)
    # exact normals of the renderer against PCA normals of the same points: planes agree
    assert point_cloud_metrics(aligned, pts, gt_normals=nrm)["nc_med"] == pytest.approx(1.0, abs=1e-6)


def test_accuracy_of_gaussian_noise_of_known_sigma():
    sigma = 0.01
    gt = grid_plane(0.001, half=0.5)  # spacing sigma / 10: the nearest distance is the height
    rng = np.random.default_rng(0)
    pred = gt[rng.choice(len(gt), 40_000, replace=False)]
    pred = pred + rng.normal(scale=sigma, size=pred.shape)
    up = lambda p: np.tile([0.0, 0.0, 1.0], (len(p), 1))  # noqa: E731 (exact normals: no 1M-point PCA)
    r = point_cloud_metrics(pred, gt, up(pred), up(gt))
    assert r["nc"] == 1.0
    assert r["acc"] == pytest.approx(sigma * np.sqrt(2 / np.pi), rel=0.03)  # E|N(0, sigma)|
    assert r["acc_med"] == pytest.approx(0.6745 * sigma, rel=0.03)  # median |N(0, sigma)|


def test_dropped_region_completeness_and_chamfer():
    step, a = 0.01, 0.5
    gt = grid_plane(step)
    pred = gt[gt[:, 0] <= a + 1e-9]  # the strip x > a is missing
    expected = np.maximum(gt[:, 0] - a, 0.0)  # nearest kept point: same row, column x = a
    r = point_cloud_metrics(pred, gt)
    assert r["acc"] == 0.0 and r["acc_med"] == 0.0
    assert r["comp"] == pytest.approx(expected.mean(), rel=1e-9)
    assert r["comp_med"] == pytest.approx(np.median(expected), abs=1e-12)
    assert chamfer_distance(pred, gt) == pytest.approx(expected.mean(), rel=1e-9)
    assert chamfer_distance(pred, gt, max_dist=0.1) == pytest.approx(np.minimum(expected, 0.1).mean(), rel=1e-9)


def test_depth_abs_rel():
    ref = np.full((2, 4, 5), 2.0)
    ref[0, 0, 0] = 0.0  # no reference: ignored
    assert depth_abs_rel(ref, ref) == 0.0
    assert depth_abs_rel(ref * 1.1, ref) == pytest.approx(0.1)
    with pytest.raises(ValueError, match="same shape"):
        depth_abs_rel(ref[0], ref)


def test_point_metrics_reject_bad_input():
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        point_cloud_metrics(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="NaN"):
        chamfer_distance(np.full((5, 3), np.nan), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="empty"):
        chamfer_distance(np.zeros((0, 3)), np.zeros((5, 3)))


def test_bbox_scale_on_a_subset_equals_subset_of_the_whole(scene):
    """The ScanNet scorer aligns a subsample with the full cloud's box: the same rows as
    aligning everything, then subsampling (FastVGGT's order)."""
    from rvggt_jax.eval import bbox_scale

    pts, _ = scene.cloud()
    gt = apply_sim3(pts, 2.0, np.eye(3), np.array([1.0, 2.0, 3.0]))
    full, s = bbox_scale(pts, gt)
    assert s == pytest.approx(2.0)
    np.testing.assert_allclose(full, gt, atol=1e-9)
    idx = np.random.default_rng(0).choice(len(pts), 100, replace=False)
    part, s2 = bbox_scale(pts[idx], gt, pred_bounds=(pts.min(0), pts.max(0)))
    np.testing.assert_allclose(part, full[idx], atol=1e-12)
    assert s2 == s
