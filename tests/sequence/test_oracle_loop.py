"""The long-sequence pipeline without trained weights: a 1,200-frame walk around a closed
corridor (`rvggt_jax.synthetic.loop_walkthrough`) predicted chunk by chunk by the oracle
(`rvggt_jax.sequence.oracle.OraclePredictor`: true geometry, random scale per chunk,
pixel noise, a 0.3-degree rotation bias per chunk), chained by `align_chunks`.

Done when (chunks of 60, overlap 10): the open chain drifts measurably, and loop closure
brings the trajectory error after Sim(3) alignment to at most 1/5 of the open chain's and
at most 1% of the trajectory's extent. With noise and bias off the chain is exact.
"""

import numpy as np
import pytest

from rvggt_jax.sequence.align import align_chunks
from rvggt_jax.sequence.chunking import plan_chunks
from rvggt_jax.sequence.oracle import OraclePredictor
from rvggt_jax.synthetic import loop_walkthrough, render

FRAMES, CHUNK, OVERLAP, BIAS_DEG = 1200, 60, 10, 0.3


def umeyama_ate(est: np.ndarray, ref: np.ndarray) -> tuple[float, np.ndarray, float, np.ndarray]:
    """RMS |ref - (s R est + t)| of camera centres est, ref [S, 3] after the least-squares
    Sim(3) (Umeyama); written here rather than taken from the package, so the pipeline's
    own alignment code is not what grades it. Returns (ate, R, s, t)."""
    mu_e, mu_r = est.mean(0), ref.mean(0)
    xe, xr = est - mu_e, ref - mu_r
    u, d, vt = np.linalg.svd(xr.T @ xe / len(est))
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ fix @ vt
    s = np.trace(np.diag(d) @ fix) / np.mean(np.sum(xe ** 2, axis=1))
    t = mu_r - s * r @ mu_e
    err = ref - (s * est @ r.T + t)
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))), r, s, t


def extent(centres: np.ndarray) -> float:
    """The largest distance between two camera centres [S, 3]."""
    return float(max(np.linalg.norm(centres - c, axis=1).max() for c in centres))


@pytest.fixture(scope="module")
def walk():
    return loop_walkthrough(FRAMES, seed=0)


@pytest.fixture(scope="module")
def runs(walk):
    """The noisy, biased chunks aligned without and with loop closure."""
    oracle = OraclePredictor(walk, noise=0.01, bias_deg=BIAS_DEG, seed=0, cache_frames=FRAMES)
    chunks = [oracle(f) for f in plan_chunks(FRAMES, CHUNK, OVERLAP)]
    return chunks, align_chunks(chunks), align_chunks(chunks, loop_closure=True, verify=oracle)


def test_walk_is_a_closed_loop_of_textured_views(walk):
    c = walk.centers
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    # it ends where it started: the last step (back to frame 0) is an ordinary step
    assert np.linalg.norm(c[-1] - c[0]) < 2 * steps.mean()
    assert steps.max() < 2 * steps.mean() and extent(c) > 10.0
    scene = walk.render(range(0, FRAMES, 97))
    assert scene.points.shape == (13, walk.height, walk.width, 3)
    assert scene.valid.mean(axis=(1, 2)).min() > 0.95
    d = scene.depth[scene.valid]
    assert 0.3 < np.median(d) < 8.0  # surfaces a few metres away
    # frames differ in colour (each wall panel has its own), not one flat texture
    assert scene.images.reshape(len(scene.images), -1).std(axis=1).min() > 10


def test_render_culls_only_what_a_camera_cannot_see(walk):
    for f in (0, 333, 777, FRAMES - 1):
        assert len(walk.visible(f)) < len(walk.primitives) / 2
        _, depth, _, _ = render(walk.extrinsics[f], walk.intrinsics, walk.height, walk.width, walk.primitives)
        np.testing.assert_array_equal(walk.render([f]).depth[0], depth)


def test_oracle_frame_scale_bend_and_determinism(walk):
    frames = list(range(400, 430))
    bent = OraclePredictor(walk, noise=0.0, bias_deg=2.0, seed=3)(frames)
    exact = OraclePredictor(walk, noise=0.0, bias_deg=0.0, seed=3)(frames)
    np.testing.assert_allclose(exact.extrinsics[0], np.eye(3, 4), atol=1e-12)
    # the true geometry up to one similarity: the points map onto the world's
    world = OraclePredictor(walk, noise=0.0, bias_deg=0.0).truth(frames)[0]
    ok = np.isfinite(world).all(-1)
    ate, _, s, _ = umeyama_ate(exact.points[ok].astype(np.float64), world[ok].astype(np.float64))
    assert ate < 1e-5 and not np.isclose(s, 1.0, atol=1e-3)
    # the bend grows from 0 at the first frame to bias_deg at the last
    rel = [e[:, :3] @ x[:, :3].T for e, x in zip(bent.extrinsics, exact.extrinsics)]
    angle = [np.rad2deg(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))) for r in rel]
    np.testing.assert_allclose(angle, 2.0 * np.arange(30) / 29, atol=1e-5)
    noisy = OraclePredictor(walk, noise=0.02, seed=3)
    a, b = noisy(frames), noisy(frames)
    np.testing.assert_array_equal(a.points, b.points)
    assert np.isnan(a.points).sum() == np.isnan(exact.points).sum()
    # another set of frames is another call: another scale and other noise
    assert not np.allclose(a.points[:29], noisy(frames[:29]).points, equal_nan=True)
    # the noise is relative to depth; outliers are far off
    depth = OraclePredictor(walk).truth(frames)[1]
    for outliers in (0.0, 0.05):
        pred = OraclePredictor(walk, noise=0.02, bias_deg=0.0, seed=3, outliers=outliers)(frames)
        rel = np.linalg.norm(pred.points - exact.points, axis=-1)[ok] * s / depth[ok]  # s: back to metres
        assert 0.01 < np.median(rel) < 0.06
        assert 0.8 * outliers - 0.002 <= np.mean(rel > 0.2) <= outliers + 0.002


def test_oracle_descriptors_recognise_places(walk):
    oracle = OraclePredictor(walk)
    d = oracle.descriptors(np.arange(FRAMES))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-5)
    # one frame, one descriptor, whichever call predicts it
    np.testing.assert_array_equal(oracle(range(500, 560)).descriptors[10], d[510])
    c = walk.centers
    near = d[3] @ d[FRAMES - 3]  # the walk's start seen again at its end
    far = [d[3] @ d[f] for f in range(200, 1000, 50) if np.linalg.norm(c[f] - c[3]) > 6.0]
    assert near > 0.8 and max(far) < 0.6


def test_loop_closure_removes_the_drift(walk, runs):
    chunks, open_chain, closed = runs
    gt = walk.centers
    size = extent(gt)
    open_ate = umeyama_ate(open_chain.centers, gt)[0]
    closed_ate = umeyama_ate(closed.centers, gt)[0]
    print(f"\n{FRAMES} frames, {len(chunks)} chunks of {CHUNK} (overlap {OVERLAP}), bias {BIAS_DEG} deg/chunk: "
          f"extent {size:.3f} m, ATE open chain {open_ate:.4f} m ({100 * open_ate / size:.3f}%), "
          f"loop-closed {closed_ate:.4f} m ({100 * closed_ate / size:.3f}%), loops "
          f"{[(e.i, e.j, e.frames) for e in closed.loops]}")
    assert open_ate > 0.005 * size  # the bias drifts; pixel noise alone gives ~0.2%
    assert closed_ate <= open_ate / 5
    assert closed_ate <= 0.01 * size
    assert any({e.i, e.j} == {0, len(chunks) - 1} for e in closed.loops)
    assert not open_chain.loops


def test_noise_and_bias_off_recover_the_trajectory_exactly():
    frames = 300
    walk = loop_walkthrough(frames, seed=1)
    oracle = OraclePredictor(walk, noise=0.0, bias_deg=0.0, seed=1, cache_frames=frames)
    chunks = [oracle(f) for f in plan_chunks(frames, CHUNK, OVERLAP)]
    gt = walk.centers
    for traj in (align_chunks(chunks), align_chunks(chunks, loop_closure=True, verify=oracle)):
        ate, r, _, _ = umeyama_ate(traj.centers, gt)
        assert ate < 1e-6 * extent(gt)
        # the cameras' orientations too: R_gt^T R_est is one rotation for every frame
        q = np.einsum("sji,sjk->sik", walk.extrinsics[:, :, :3], traj.extrinsics[:, :, :3])
        np.testing.assert_allclose(q, np.broadcast_to(r, q.shape), atol=1e-6)
