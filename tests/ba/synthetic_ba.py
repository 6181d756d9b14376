"""Shared pieces of the bundle-adjustment tests: a synthetic scene with exact cameras,
perturbed cameras, an exact tracker, and gauge-free pose errors."""

from __future__ import annotations

import numpy as np

from rvggt_jax.ba.triangulate import project
from rvggt_jax.synthetic import make_scene, ray_cast


def rotation(axis_angle) -> np.ndarray:
    """Rodrigues: [3] axis * angle (radians) -> [3, 3]."""
    v = np.asarray(axis_angle, np.float64)
    a = np.linalg.norm(v)
    if a == 0:
        return np.eye(3)
    k = v / a
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def centers(ext: np.ndarray) -> np.ndarray:
    return -np.einsum("sji,sj->si", ext[:, :, :3], ext[:, :, 3])


def perturb(ext: np.ndarray, rng: np.random.Generator, rot_deg: float, trans_frac: float) -> np.ndarray:
    """Every camera but the first turned by `rot_deg` about a random axis and its centre
    moved by `trans_frac` of the mean camera distance from the first, in a random
    direction (the first stays: it is the model's reference frame, exact by definition)."""
    out = ext.copy()
    c = centers(ext)
    scale = np.linalg.norm(c - c[0], axis=1).mean()
    for i in range(1, len(ext)):
        axis = rng.normal(size=3)
        r = rotation(axis / np.linalg.norm(axis) * np.radians(rot_deg)) @ ext[i, :, :3]
        d = rng.normal(size=3)
        ci = c[i] + trans_frac * scale * d / np.linalg.norm(d)
        out[i] = np.concatenate([r, (-r @ ci)[:, None]], axis=1)
    return out


def relative_rotation_error_deg(ext: np.ndarray, truth: np.ndarray) -> float:
    """Mean over frame pairs of the angle between R_i R_j^T and its truth (degrees): blind
    to the gauge (any similarity of the whole scene)."""
    errs = []
    for i in range(len(ext)):
        for j in range(i + 1, len(ext)):
            a = ext[i, :, :3] @ ext[j, :, :3].T
            b = truth[i, :, :3] @ truth[j, :, :3].T
            cos = (np.trace(a @ b.T) - 1) / 2
            errs.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return float(np.mean(errs))


def center_error(ext: np.ndarray, truth: np.ndarray) -> float:
    """Mean camera-centre error after the best similarity alignment (Umeyama), relative to
    the mean distance of the true centres from their centroid: blind to the gauge."""
    x, y = centers(ext), centers(truth)
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    u, d, vt = np.linalg.svd(yc.T @ xc / len(x))
    sgn = np.diag([1, 1, np.sign(np.linalg.det(u @ vt))])
    r = u @ sgn @ vt
    s = np.trace(np.diag(d) @ sgn) / (xc ** 2).sum(1).mean()
    aligned = s * xc @ r.T + my
    return float(np.linalg.norm(aligned - y, axis=1).mean() / np.linalg.norm(yc, axis=1).mean())


def scene(frames: int = 6, height: int = 72, width: int = 96, seed: int = 3):
    return make_scene(frames=frames, height=height, width=width, seed=seed)


class ExactTracker:
    """A tracker with exact answers for a synthetic scene: it recognises the frame order of
    the images it is given (by comparing them with the scene's), casts the query pixels of
    the first into the scene, and projects the hits into every frame with the true
    cameras. Visibility 1 where the projection is in the image and in front. Counts its
    calls and records the orders it saw."""

    def __init__(self, sc, noise_px: float = 0.0, seed: int = 0):
        self.sc = sc
        self.images = sc.images.transpose(0, 3, 1, 2).astype(np.float32) / 255.0
        self.noise_px = noise_px
        self.rng = np.random.default_rng(seed)
        self.orders: list[list[int]] = []

    def __call__(self, images: np.ndarray, queries: np.ndarray):
        order = [int(np.argmin([np.abs(self.images - im).sum(axis=(1, 2, 3))])) for im in images]
        self.orders.append(order)
        e, k = self.sc.extrinsics[order], self.sc.intrinsics[order]
        r, t = e[0, :, :3], e[0, :, 3]
        hom = np.concatenate([queries, np.ones((len(queries), 1))], axis=1)
        dirs = hom @ np.linalg.inv(k[0]).T @ r  # rows: R^T K^-1 [x, y, 1]
        hit, _, _ = ray_cast(-r.T @ t, dirs, self.sc.primitives)
        world = -r.T @ t + np.where(np.isfinite(hit), hit, np.nan)[:, None] * dirs
        uv, z = project(e, k, world)
        h, w = images.shape[2:]
        vis = (np.isfinite(uv).all(-1) & (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0)
               & (uv[..., 1] < h)).astype(np.float32)
        uv = uv + self.noise_px * self.rng.normal(size=uv.shape)
        return np.nan_to_num(uv, nan=-1.0), vis, vis.copy()
