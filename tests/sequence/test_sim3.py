"""Weighted Umeyama and the robust (Huber IRLS) sim3_align: recovery with gross outliers,
unusable points left out, bad inputs refused."""

import numpy as np
import pytest

from rvggt_jax.errors import InputError
from rvggt_jax.sequence import Sim3, sim3_align, sim3_align_report, umeyama


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _random_sim3(rng: np.random.Generator) -> Sim3:
    return Sim3(float(np.exp(rng.uniform(-1.5, 1.5))), _random_rotation(rng), rng.normal(0, 3, 3))


def _errors(est: Sim3, true: Sim3) -> tuple[float, float, float]:
    """(relative scale error, rotation error in degrees, translation error / |t|)."""
    cos = np.clip((np.trace(est.rotation.T @ true.rotation) - 1) / 2, -1, 1)
    return (abs(est.scale / true.scale - 1), float(np.degrees(np.arccos(cos))),
            float(np.linalg.norm(est.translation - true.translation) / np.linalg.norm(true.translation)))


def _outlier_problem(seed: int, n: int = 1000, outliers: float = 0.2, noise: float = 0.01):
    """n points, `noise`: Gaussian noise of RMS norm 1% of the dst cloud's RMS radius;
    `outliers` of dst replaced by points uniform in a box 5 times the cloud's extent."""
    rng = np.random.default_rng(seed)
    true = _random_sim3(rng)
    src = rng.uniform(-1, 1, (n, 3))
    dst = true.apply(src)
    radius = np.sqrt(((dst - dst.mean(axis=0)) ** 2).sum(axis=1).mean())
    dst += rng.normal(0, noise * radius / np.sqrt(3), dst.shape)
    bad = rng.choice(n, int(outliers * n), replace=False)
    lo, hi = dst.min(axis=0), dst.max(axis=0)
    dst[bad] = (lo + hi) / 2 + rng.uniform(-2.5, 2.5, (len(bad), 3)) * (hi - lo).max()
    return src, dst, true, bad


def test_recovers_sim3_with_20_percent_gross_outliers():
    src, dst, true, bad = _outlier_problem(seed=7)
    fit = sim3_align_report(src, dst)
    ds, dr, dt = _errors(fit.sim3, true)
    print(f"sim3_align errors: scale {ds:.2e} relative, rotation {dr:.4f} deg, translation {dt:.2e} of |t|")
    assert ds < 1e-3 and dr < 0.1 and dt < 1e-2
    # The outliers are gross: the closed form alone is far off on the same data.
    ds0, dr0, _ = _errors(umeyama(src, dst), true)
    assert ds0 > 0.05 or dr0 > 1.0
    # The outliers are what the fit leaves out; the inliers nearly all stay in.
    good = np.setdiff1d(np.arange(len(src)), bad)
    r = np.linalg.norm(dst - fit.sim3.apply(src), axis=1)
    assert (r[bad] > fit.delta).mean() > 0.95 and (r[good] <= fit.delta).mean() > 0.95
    assert fit.used == len(src) and abs(fit.inliers - len(good)) < 0.05 * len(src)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_recovery_other_draws(seed):
    src, dst, true, _ = _outlier_problem(seed)
    ds, dr, dt = _errors(sim3_align(src, dst), true)
    assert ds < 1e-3 and dr < 0.1 and dt < 1e-2


def test_umeyama_exact_and_weighted():
    rng = np.random.default_rng(0)
    true = _random_sim3(rng)
    src = rng.normal(size=(50, 3))
    dst = true.apply(src)
    np.testing.assert_allclose(umeyama(src, dst).matrix(), true.matrix(), atol=1e-10)
    # Corrupted rows with zero weight must not count, whatever their values.
    dst2 = dst.copy()
    dst2[:10] += rng.normal(0, 5, (10, 3))
    w = np.ones(50)
    w[:10] = 0
    np.testing.assert_allclose(umeyama(src, dst2, w).matrix(), true.matrix(), atol=1e-10)
    assert not np.allclose(umeyama(src, dst2).matrix(), true.matrix(), atol=1e-3)


def test_umeyama_planar_and_reflection():
    rng = np.random.default_rng(1)
    true = _random_sim3(rng)
    src = np.c_[rng.normal(size=(30, 2)), np.zeros(30)]  # a plane: still determined
    np.testing.assert_allclose(umeyama(src, true.apply(src)).matrix(), true.matrix(), atol=1e-10)
    # A mirrored cloud has no rotation that maps it: the result stays a rotation.
    cloud = rng.normal(size=(40, 3))
    t = umeyama(cloud, cloud * np.array([1, 1, -1]))
    assert np.linalg.det(t.rotation) == pytest.approx(1.0)


def test_scale_free_delta():
    """The Huber delta follows the data's units: the same problem in units 1000x larger
    gives the same rotation, 1000x the scale and translation."""
    src, dst, _, _ = _outlier_problem(seed=4)
    a, b = sim3_align(src, dst), sim3_align(src, 1000.0 * dst)
    assert b.scale == pytest.approx(1000 * a.scale, rel=1e-9)
    np.testing.assert_allclose(b.rotation, a.rotation, atol=1e-9)
    np.testing.assert_allclose(b.translation, 1000 * a.translation, rtol=1e-9, atol=1e-9)


def test_unusable_points_are_left_out():
    src, dst, true, _ = _outlier_problem(seed=5, n=400)
    ref = sim3_align(src, dst)
    rng = np.random.default_rng(5)
    junk_src, junk_dst = rng.normal(size=(40, 3)) * 100, rng.normal(size=(40, 3)) * 100
    junk_src[:10, 1] = np.nan
    junk_dst[10:20, 0] = np.inf
    w = np.r_[np.ones(400), np.ones(20), np.full(10, np.nan), np.full(10, -1.0)]
    fit = sim3_align_report(np.r_[src, junk_src], np.r_[dst, junk_dst], w)
    assert fit.used == 400
    np.testing.assert_allclose(fit.sim3.matrix(), ref.matrix(), atol=1e-12)
    assert _errors(fit.sim3, true)[1] < 0.1


def test_bad_inputs_raise_input_error():
    pts = np.random.default_rng(0).normal(size=(10, 3))
    few = pts.copy()
    few[2:] = np.nan
    with pytest.raises(InputError, match="at least 3 usable points.*got 2"):
        sim3_align(few, pts)
    with pytest.raises(InputError, match="at least 3"):
        sim3_align(pts, pts, np.r_[np.ones(2), np.zeros(8)])
    with pytest.raises(InputError, match=r"\[N, 3\]"):
        sim3_align(pts[:, :2], pts[:, :2])
    with pytest.raises(InputError, match=r"\[N, 3\]"):
        umeyama(pts, pts[:9])
    with pytest.raises(InputError, match="weights must be"):
        sim3_align(pts, pts, np.ones(9))
    line = np.outer(np.arange(10.0), [1, 2, 3])
    with pytest.raises(InputError, match="line"):
        umeyama(line, line)
    with pytest.raises(InputError, match="delta"):
        sim3_align(pts, pts, delta=-1.0)
