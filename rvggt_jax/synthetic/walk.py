"""A long walk around a closed corridor (`loop_walkthrough` -> `LoopWalk`), for the
long-sequence pipeline (`rvggt_jax.sequence`): it holds only the cameras and the
primitives, and renders any subset of frames on demand."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from rvggt_jax.synthetic.render import Box, Rect, render
from rvggt_jax.synthetic.scenes import SyntheticScene, _rot_y, camera_centers, look_at


@dataclasses.dataclass(frozen=True, eq=False)
class LoopWalk:
    """A walk of S frames around a closed corridor (walls, floor, ceiling, boxes): frame 0
    and frame S-1 are one step apart, so the walk ends where it started.

    extrinsics  [S, 3, 4] float64 world-to-camera (OpenCV; world y points down)
    intrinsics  [3, 3] float64 pinhole, in pixels of a `height` x `width` image
    arc         [S] float64 each camera's distance (m) along the loop's centreline
    primitives  the whole loop's Rect and Box primitives; `prim_arc` [P] the arc position
                of each (NaN: floor and ceiling, seen from everywhere), `prim_ball` [P, 4]
                a ball around each (centre, radius; inf for floor and ceiling)
    length      the centreline's length (m); `view` how far ahead (m) a camera sees
    """

    extrinsics: np.ndarray
    intrinsics: np.ndarray
    height: int
    width: int
    arc: np.ndarray
    primitives: tuple
    prim_arc: np.ndarray
    prim_ball: np.ndarray
    length: float
    view: float = 25.0

    def __len__(self) -> int:
        return len(self.extrinsics)

    @property
    def centers(self) -> np.ndarray:
        """[S, 3] true camera centres."""
        return camera_centers(self.extrinsics)

    def visible(self, frame: int) -> tuple:
        """The primitives frame `frame` may see: those from 2 m behind to `view` ahead
        along the loop (the corridor's bends hide the rest), so that a frame's render
        costs the same however long the loop is, and of those the ones whose ball meets
        the camera's frustum."""
        ahead = (self.prim_arc - self.arc[frame]) % self.length
        near = np.isnan(self.prim_arc) | (ahead <= self.view) | (ahead >= self.length - 2.0)
        e = self.extrinsics[frame]
        c = self.prim_ball[:, :3] @ e[:, :3].T + e[:, 3]
        r = self.prim_ball[:, 3]
        k = self.intrinsics
        with np.errstate(invalid="ignore"):  # inf balls: kept by the isnan test above
            inside = c[:, 2] > -r
            for axis, half in ((0, self.width / 2 / k[0, 0]), (1, self.height / 2 / k[1, 1])):
                inside &= np.abs(c[:, axis]) - half * c[:, 2] <= r * np.hypot(1.0, half)
        keep = near & (inside | np.isnan(self.prim_arc))
        return tuple(p for p, k in zip(self.primitives, keep) if k)

    def render(self, frames: Sequence[int]) -> SyntheticScene:
        """Render frames `frames` [F] only: a `SyntheticScene` of F frames (images,
        depth, points, normals [F, H, W, ...], extrinsics [F, 3, 4], intrinsics [F, 3, 3])."""
        frames = [int(f) for f in frames]
        outs = [render(self.extrinsics[f], self.intrinsics, self.height, self.width, self.visible(f)) for f in frames]
        imgs, depth, pts, nrm = (np.stack(x) for x in zip(*outs))
        return SyntheticScene(name="loop_walk", images=imgs, depth=depth, points=pts, normals=nrm,
                              extrinsics=self.extrinsics[frames],
                              intrinsics=np.repeat(self.intrinsics[None], len(frames), axis=0))


def _loop_centreline(length: float, rng: np.random.Generator):
    """A smooth closed curve in the horizontal x-z plane, polar radius 1 + 0.12 sin(2a + p)
    + 0.06 sin(3a + q) scaled to `length` metres (bends of radius >= length / 10); a loop
    of 120 m or more also winds n = length / 40 times (bends of radius >= 4 m), so that a
    long loop is no straighter, and a camera sees no farther, than a short one. Returns
    (arc [N+1], points [N+1, 2], unit tangents [N+1, 2]) at N samples equally spaced in
    angle, the last one the first."""
    p, q = rng.uniform(0, 2 * np.pi, 2)
    n = int(round(length / 40.0)) if length >= 120.0 else 0
    # amplitude (lambda / 2 pi)^2 / 8 m for a wavelength lambda (bends of radius >= 8 m), at unit radius
    w = (length / n / (2 * np.pi)) ** 2 / 8.0 * 2 * np.pi / length if n else 0.0
    a = np.linspace(0.0, 2 * np.pi, max(8192, int(20 * length)) + 1)
    r = 1.0 + 0.12 * np.sin(2 * a + p) + 0.06 * np.sin(3 * a + q) + w * np.sin(n * a + p + q)
    dr = 0.24 * np.cos(2 * a + p) + 0.18 * np.cos(3 * a + q) + w * n * np.cos(n * a + p + q)
    xz = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    d = np.stack([dr * np.cos(a) - r * np.sin(a), dr * np.sin(a) + r * np.cos(a)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=1))])
    k = length / arc[-1]
    return arc * k, xz * k, d / np.linalg.norm(d, axis=1, keepdims=True)


def _on_loop(arc, xz, tangent, s):
    """Centreline points [N, 2] and unit tangents [N, 2] at arc positions s [N] (mod length)."""
    s = np.asarray(s, np.float64) % arc[-1]
    pts = np.stack([np.interp(s, arc, xz[:, i]) for i in range(2)], axis=1)
    tan = np.stack([np.interp(s, arc, tangent[:, i]) for i in range(2)], axis=1)
    return pts, tan / np.linalg.norm(tan, axis=1, keepdims=True)


def _corridor(arc, xz, tangent, rng, width: float, segment: float, box_rate: float):
    """Walls ([2 per segment] Rects from floor y = 1 to ceiling y = -1.5), one floor and
    one ceiling Rect over the whole loop, and boxes along the walls. Returns (primitives,
    prim_arc [P], prim_ball [P, 4]) as `LoopWalk` holds them."""
    n = max(8, int(round(arc[-1] / segment)))
    s = np.arange(n + 1) * arc[-1] / n
    c, t = _on_loop(arc, xz, tangent, s)
    side = np.stack([-t[:, 1], t[:, 0]], axis=1)  # horizontal unit normal of the centreline
    lo, hi = xz.min(axis=0) - width, xz.max(axis=0) + width
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    prims: list = [Rect((mid[0], 1.0, mid[1]), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), tuple(half), (0.8, 0.75, 0.6), 2.0),
                   Rect((mid[0], -1.5, mid[1]), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), tuple(half), (0.7, 0.8, 0.9), 1.0)]
    where = [np.nan, np.nan]
    for k in range(n):
        for sign in (-1.0, 1.0):
            a, b = c[k] + sign * width / 2 * side[k], c[k + 1] + sign * width / 2 * side[k + 1]
            u = np.array([b[0] - a[0], 0.0, b[1] - a[1]])
            lu = np.linalg.norm(u)
            # 2 cm longer than the gap so that the bent wall has no cracks
            prims.append(Rect(((a[0] + b[0]) / 2, -0.25, (a[1] + b[1]) / 2), tuple(u / lu), (0.0, 1.0, 0.0),
                              (lu / 2 + 0.02, 1.25), tuple(rng.uniform(0.3, 1.0, 3)), 3.0))
            where.append((s[k] + s[k + 1]) / 2)
        if rng.uniform() < box_rate:
            h = rng.uniform(0.15, 0.35, 3)
            m = (c[k] + c[k + 1]) / 2 + rng.choice([-1.0, 1.0]) * (width / 2 - 0.55) * (side[k] + side[k + 1]) / 2
            prims.append(Box((m[0], 1.0 - h[1], m[1]), _rot_y(rng.uniform(0, 90)), tuple(h),
                             tuple(rng.uniform(0.3, 1.0, 3)), 5.0))
            where.append((s[k] + s[k + 1]) / 2)
    ball = [(p.center, np.hypot(*p.half)) if isinstance(p, Rect) else (p.center, np.linalg.norm(p.half))
            for p in prims[2:]]
    ball = np.array([[0, 0, 0, np.inf]] * 2 + [[*c, r] for c, r in ball], np.float64)
    return tuple(prims), np.asarray(where), ball


def loop_walkthrough(frames: int = 1200, seed: int = 0, *, height: int = 24, width: int = 32,
                     length: float | None = None, corridor: float = 3.0, segment: float = 1.5,
                     box_rate: float = 0.6, focal: float | None = None) -> LoopWalk:
    """A walk of `frames` cameras around a closed corridor `corridor` metres wide whose
    centreline is `length` metres long (default max(40, 0.05 x frames): 5 cm per step),
    walls in `segment`-metre panels of random colours and boxes along them. The cameras
    stand 1.35 m above the floor, face along the direction of motion pitched 8 degrees
    down, and wobble a little sideways, up and down and in heading. Images are `height` x
    `width` with focal `focal` pixels (default 0.9 x width), principal point at the centre.
    Deterministic in `seed`."""
    if frames < 2 or height < 2 or width < 2:
        raise ValueError(f"need frames >= 2 and an image of at least 2x2 pixels; got {frames}, {width}x{height}")
    length = max(40.0, 0.05 * frames) if length is None else float(length)
    if length < 40.0:
        raise ValueError(f"the loop must be at least 40 m long (its bends would be tighter than the corridor); "
                         f"got {length}")
    rng = np.random.default_rng(seed)
    arc, xz, tangent = _loop_centreline(length, rng)
    prims, prim_arc, prim_ball = _corridor(arc, xz, tangent, rng, corridor, segment, box_rate)
    s = np.arange(frames) * length / frames
    c, t = _on_loop(arc, xz, tangent, s)
    ph = rng.uniform(0, 2 * np.pi, 3)
    side = np.stack([-t[:, 1], t[:, 0]], axis=1)
    c = c + 0.12 * np.sin(2 * np.pi * s / 7.3 + ph[0])[:, None] * side
    y = -0.35 + 0.03 * np.sin(2 * np.pi * s / 3.1 + ph[1])
    yaw = np.deg2rad(4.0) * np.sin(2 * np.pi * s / 5.3 + ph[2])
    fwd = np.cos(yaw)[:, None] * t + np.sin(yaw)[:, None] * side
    centres = np.stack([c[:, 0], y, c[:, 1]], axis=1)
    look = np.stack([fwd[:, 0], np.full(frames, np.tan(np.deg2rad(8.0))), fwd[:, 1]], axis=1)
    ext = np.stack([look_at(p, p + d) for p, d in zip(centres, look)])
    f = 0.9 * width if focal is None else float(focal)
    k = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return LoopWalk(ext, k, height, width, s, prims, prim_arc, prim_ball, length)
