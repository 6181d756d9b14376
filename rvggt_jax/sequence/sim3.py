"""Similarity transforms x -> s R x + t between the coordinate frames of chunks, and
their estimation from corresponding points: the closed-form weighted Umeyama solution
(`umeyama`) and its robust refinement by IRLS with a Huber loss (`sim3_align`,
`sim3_align_report`).

Points that are not finite, and points whose weight is not finite or not positive, are
left out (a chunk's point maps hold NaN where a pixel has no point); fewer than 3 usable
points, or usable points on one line (the rotation about it is then free), raise
`InputError`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rvggt_jax.errors import InputError

__all__ = ["Sim3", "Sim3Fit", "sim3_align", "sim3_align_report", "umeyama"]

# The Huber delta when none is given, as a multiple of the median residual of the current
# fit: about 3.5 noise standard deviations for Gaussian 3-D residuals (their norm's median
# is about 1.54 sigma), so inliers keep full weight while a gross outlier's pull on the
# fit is bounded by delta.
HUBER_MEDIAN_FACTOR = 2.0
# Residuals beyond this many Huber deltas (about 35 noise sigmas) are gross outliers, left
# out once the Huber fit has converged.
GROSS_OUTLIER_FACTOR = 10.0
# Smallest Huber delta, relative to the target cloud's RMS spread: exact correspondences
# have a median residual of rounding size, and a delta of 0 would divide by 0.
_DELTA_FLOOR = 1e-12


@dataclasses.dataclass(frozen=True, eq=False)
class Sim3:
    """x -> scale * rotation @ x + translation. scale > 0 (float), rotation [3, 3] in
    SO(3), translation [3]."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", float(self.scale))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "translation", np.asarray(self.translation, dtype=np.float64).reshape(3))

    @classmethod
    def identity(cls) -> "Sim3":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> "Sim3":
        """From a [4, 4] matrix [[s R, t], [0, 1]]."""
        m = np.asarray(m, dtype=np.float64)
        s = float(np.cbrt(np.linalg.det(m[:3, :3])))
        return cls(s, m[:3, :3] / s, m[:3, 3])

    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def apply(self, points) -> np.ndarray:
        """points [..., 3] -> [..., 3] float64."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    def __matmul__(self, other: "Sim3") -> "Sim3":
        """self @ other: x -> self(other(x))."""
        return Sim3(self.scale * other.scale, self.rotation @ other.rotation,
                    self.scale * self.rotation @ other.translation + self.translation)

    def inverse(self) -> "Sim3":
        rt = self.rotation.T
        return Sim3(1.0 / self.scale, rt, -(rt @ self.translation) / self.scale)

    def transform_extrinsics(self, extrinsics) -> np.ndarray:
        """World-to-camera extrinsics [..., 3, 4] of cameras in this transform's source
        frame -> the same cameras' extrinsics in its target frame, in the target's units:
        a camera x_c = R x + t seen from target coordinates y = s Q x + u has
        x_c' = s x_c = (R Q^T) y + (s t - R Q^T u)."""
        e = np.asarray(extrinsics, dtype=np.float64)
        r = e[..., :3] @ self.rotation.T
        t = self.scale * e[..., 3] - np.einsum("...ij,j->...i", r, self.translation)
        return np.concatenate([r, t[..., None]], axis=-1)


@dataclasses.dataclass(frozen=True, eq=False)
class Sim3Fit:
    """A robust alignment and how well it fits.

    sim3        the transform src -> dst
    residual    robust RMS residual: the confidence-weighted RMS of the inliers' residuals
                |dst - sim3(src)|, in dst's units
    inliers     how many usable points have a residual of at most `delta`
    used        how many points were usable (finite, positive finite weight)
    delta       the Huber delta of the last IRLS iteration, in dst's units
    spread      the weighted RMS distance of the usable dst points from their centroid:
                the cloud's size in dst's units, to judge `residual` by
    iterations  IRLS iterations run
    """

    sim3: Sim3
    residual: float
    inliers: int
    used: int
    delta: float
    spread: float
    iterations: int

    @property
    def relative_residual(self) -> float:
        """`residual` / `spread`: unit-free (chunks have arbitrary scales)."""
        return self.residual / self.spread if self.spread > 0 else float("inf")


def _usable(src, dst, weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """src, dst [N, 3] and weights [N] (or None) -> the usable rows [M, 3], [M, 3] and
    their weights [M] (float64); `InputError` on wrong shapes or fewer than 3 usable rows."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or dst.shape != src.shape:
        raise InputError(f"sim3 alignment needs src and dst of the same shape [N, 3]; got "
                         f"{list(src.shape)} and {list(dst.shape)}")
    if weights is None:
        w = np.ones(len(src))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(src),):
            raise InputError(f"sim3 alignment weights must be [N] = [{len(src)}]; got {list(w.shape)}")
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1) & np.isfinite(w) & (w > 0)
    if keep.sum() < 3:
        raise InputError(f"sim3 alignment needs at least 3 usable points (finite in src and dst, with a "
                         f"finite positive weight); got {int(keep.sum())} of {len(src)}")
    return src[keep], dst[keep], w[keep]


def _weighted_umeyama(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> Sim3:
    """The closed-form least-squares Sim(3) minimising sum_i w_i |dst_i - (s R src_i + t)|^2
    (Umeyama 1991, with weights): weighted centroids, weighted cross-covariance, its SVD
    with the reflection fixed, s = trace(D S) / weighted variance of src. Rows must
    already be usable; `InputError` when src is one point or one line."""
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov_s = (xs * w[:, None]).T @ xs
    ev = np.linalg.eigvalsh(cov_s)
    if ev[-1] <= 0 or ev[-2] <= 1e-12 * ev[-1]:
        raise InputError("sim3 alignment needs src points that span a plane or a volume; the usable "
                         "points are one point or lie on one line, so the rotation about it is unknown")
    sigma = (xd * w[:, None]).T @ xs
    u, d, vt = np.linalg.svd(sigma)
    fix = np.ones(3)
    # A reflection would fit better when det(U V^T) = -1 (noisy or planar clouds): flip the
    # axis of the smallest singular value instead.
    fix[2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rotation = (u * fix) @ vt
    scale = float(d @ fix / np.trace(cov_s))
    if not scale > 0:
        raise InputError("sim3 alignment found no positive scale: src and dst do not correspond")
    return Sim3(scale, rotation, mu_d - scale * rotation @ mu_s)


def umeyama(src, dst, weights=None) -> Sim3:
    """Closed-form weighted least-squares similarity src -> dst (Umeyama).

    src, dst  [N, 3] corresponding points; dst ~ scale * rotation @ src + translation
    weights   [N] non-negative, or None for equal weights
    Rows with a non-finite point or a non-finite or non-positive weight are left out.
    Not robust: one gross outlier moves it (use `sim3_align`)."""
    return _weighted_umeyama(*_usable(src, dst, weights))


def _spread(dst: np.ndarray, w: np.ndarray) -> float:
    mu = (w @ dst) / w.sum()
    return float(np.sqrt((w @ ((dst - mu) ** 2).sum(axis=1)) / w.sum()))


def _change(a: Sim3, b: Sim3, spread: float) -> float:
    return max(abs(a.scale - b.scale) / b.scale, float(np.abs(a.rotation - b.rotation).max()),
               float(np.abs(a.translation - b.translation).max()) / max(spread, 1e-300))


def _irls(src, dst, w, fit: Sim3, huber_delta, iterations: int, tol: float, spread: float,
          cutoff: float | None) -> tuple[Sim3, np.ndarray, float, int]:
    """Huber IRLS from `fit`; with `cutoff`, residuals above cutoff * delta get weight 0.
    -> (fit, residuals [M], last delta, iterations run)."""
    floor = _DELTA_FLOOR * max(spread, 1e-300)
    r = np.linalg.norm(dst - fit.apply(src), axis=1)
    d = huber_delta(r)
    done = 0
    for done in range(1, iterations + 1):
        h = np.where(r <= d, 1.0, d / np.maximum(r, floor))
        if cutoff is not None:
            h[r > cutoff * d] = 0.0
        new = _weighted_umeyama(src, dst, w * h)
        moved = _change(new, fit, spread)
        fit = new
        r = np.linalg.norm(dst - fit.apply(src), axis=1)
        d = huber_delta(r)
        if moved < tol:
            break
    return fit, r, d, done


def sim3_align_report(src, dst, weights=None, *, delta: float | None = None, iterations: int = 30,
                      tol: float = 1e-10) -> Sim3Fit:
    """Robust similarity src -> dst with its fit statistics (`Sim3Fit`).

    src, dst  [N, 3]; weights [N] non-negative confidences (None: equal). Unusable rows
    (non-finite point, non-finite or non-positive weight) are left out.

    Confidence-weighted IRLS with a Huber loss, started from the weighted Umeyama
    solution: each iteration solves the weighted Umeyama problem with weights
    `weights * h(r)`, h(r) = 1 for a residual r <= delta and delta / r above it.
    delta: the given value (dst's units), or, when None, `HUBER_MEDIAN_FACTOR` (2) times
    the median residual of the current fit, re-estimated every iteration (so it follows
    the point cloud's units and tightens as the fit improves), never below 1e-12 times the
    dst cloud's RMS spread. Once the Huber fit has converged, residuals above
    `GROSS_OUTLIER_FACTOR` (10) times delta are gross outliers and get weight 0 for a
    second IRLS run: under Huber alone each such point still pulls with force delta,
    which biases the scale by about 0.1% at 20% gross outliers. Each run stops after
    `iterations` iterations or once the transform changes by less than `tol` (relative)."""
    if delta is not None and not (np.isfinite(delta) and delta > 0):
        raise InputError(f"sim3_align delta must be a positive finite distance or None; got {delta!r}")
    if iterations < 0:
        raise InputError(f"sim3_align iterations must be >= 0; got {iterations}")
    src, dst, w = _usable(src, dst, weights)
    spread = _spread(dst, w)
    floor = _DELTA_FLOOR * max(spread, 1e-300)

    def huber_delta(r: np.ndarray) -> float:
        return float(delta) if delta is not None else max(HUBER_MEDIAN_FACTOR * float(np.median(r)), floor)

    fit = _weighted_umeyama(src, dst, w)
    fit, r, d, huber_its = _irls(src, dst, w, fit, huber_delta, iterations, tol, spread, None)
    fit, r, d, cut_its = _irls(src, dst, w, fit, huber_delta, iterations, tol, spread, GROSS_OUTLIER_FACTOR)
    inl = r <= d
    rms = float(np.sqrt((w[inl] @ r[inl] ** 2) / w[inl].sum())) if inl.any() else float("inf")
    return Sim3Fit(fit, rms, int(inl.sum()), len(src), d, spread, huber_its + cut_its)


def sim3_align(src, dst, weights=None, *, delta: float | None = None, iterations: int = 30) -> Sim3:
    """Robust similarity src -> dst: dst ~ scale * rotation @ src + translation.

    src, dst [N, 3]; weights [N] non-negative confidences or None. Confidence-weighted
    IRLS with a Huber loss from the closed-form weighted Umeyama fit (the rule for delta:
    `sim3_align_report`); non-finite points and non-finite / negative weights are left
    out; fewer than 3 usable points raise `InputError`."""
    return sim3_align_report(src, dst, weights, delta=delta, iterations=iterations).sim3
