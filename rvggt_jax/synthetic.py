"""Procedural scenes with exact ground truth: textured planes and boxes seen by known
pinhole cameras along a path, rendered by ray casting in numpy.

    scene = make_scene(frames=6, height=60, width=80, seed=0)
    scene.images      [S, H, W, 3] uint8      rendered colours
    scene.depth       [S, H, W] float32       z in the camera frame (0 where a ray hits nothing)
    scene.points      [S, H, W, 3] float32    world points of the pixels (NaN where no hit)
    scene.normals     [S, H, W, 3] float32    world unit normals of the hit surfaces
    scene.extrinsics  [S, 3, 4] float64       world-to-camera [R | t], OpenCV (x right, y down, z forward)
    scene.intrinsics  [S, 3, 3] float64       pixels; pixel (col, row) is the ray K^-1 [col, row, 1]

The pixel convention is `rvggt_jax.geometry.depth_to_cam_points`'s (integer pixel
coordinates are pixel centres), so unprojecting `depth` with the cameras gives back
`points` to float precision. Used by the evaluation tests (every metric and reader is
checked on these scenes) and meant for fine-tuning data as well.

`write_scene(scene, fmt, root)` stores a scene in one of the evaluation datasets'
on-disk formats (`rvggt_jax.eval.datasets.FORMATS`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["Box", "Rect", "SyntheticScene", "look_at", "make_scene", "orbit_cameras", "ray_cast", "render",
           "write_scene"]


@dataclasses.dataclass(frozen=True)
class Rect:
    """A textured rectangle: centre [3], in-plane unit axes u, v [3] (orthogonal), half
    sizes (a along u, b along v). Its normal is u x v."""

    center: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    half: tuple[float, float]
    color: tuple[float, float, float]
    freq: float = 4.0


@dataclasses.dataclass(frozen=True)
class Box:
    """A textured box: centre [3], rotation [3, 3] (columns = the box axes in the
    world), half extents [3]."""

    center: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]
    half: tuple[float, float, float]
    color: tuple[float, float, float]
    freq: float = 6.0


@dataclasses.dataclass
class SyntheticScene:
    """Rendered frames and their exact geometry; see the module docstring for shapes."""

    name: str
    images: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    extrinsics: np.ndarray
    intrinsics: np.ndarray
    primitives: tuple = ()

    @property
    def valid(self) -> np.ndarray:
        """[S, H, W] bool: pixels whose ray hits a surface."""
        return self.depth > 0

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """All hit pixels' world points [N, 3] and normals [N, 3] (float64)."""
        m = self.valid
        return self.points[m].astype(np.float64), self.normals[m].astype(np.float64)


# ---------------------------------------------------------------------------------------
# ray casting
# ---------------------------------------------------------------------------------------


def _texture(uv: np.ndarray, color: np.ndarray, freq: float) -> np.ndarray:
    """Colour [N, 3] in [0, 1] of surface coordinates uv [N, 2]: a checkerboard times a
    smooth ripple, so that every patch of a surface is distinct (matchable)."""
    checker = (np.floor(uv[:, 0] * freq) + np.floor(uv[:, 1] * freq)) % 2
    ripple = 0.5 + 0.5 * np.sin(7.3 * uv[:, 0] + 3.1 * np.cos(5.7 * uv[:, 1]))
    shade = 0.45 + 0.35 * checker + 0.2 * ripple
    return np.clip(color[None, :] * shade[:, None], 0.0, 1.0)


def _hit_rect(o: np.ndarray, d: np.ndarray, r: Rect):
    c, u, v = (np.asarray(x, np.float64) for x in (r.center, r.u, r.v))
    n = np.cross(u, v)
    denom = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((c - o) @ n) / denom
    p = o[None, :] + t[:, None] * d
    s, q = (p - c) @ u, (p - c) @ v
    ok = np.isfinite(t) & (t > 1e-6) & (np.abs(s) <= r.half[0]) & (np.abs(q) <= r.half[1])
    t = np.where(ok, t, np.inf)
    normal = np.broadcast_to(n, d.shape)
    return t, normal, np.stack([s, q], axis=1)


def _hit_box(o: np.ndarray, d: np.ndarray, b: Box):
    rot = np.asarray(b.rotation, np.float64)
    h = np.asarray(b.half, np.float64)
    ol = rot.T @ (o - np.asarray(b.center, np.float64))
    dl = d @ rot
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-h[None, :] - ol[None, :]) / dl
        t2 = (h[None, :] - ol[None, :]) / dl
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    lo = np.where(np.isnan(lo), -np.inf, lo)
    hi = np.where(np.isnan(hi), np.inf, hi)
    t_near, t_far = lo.max(axis=1), hi.min(axis=1)
    ok = (t_far >= t_near) & (t_near > 1e-6)  # cameras are outside every box
    t = np.where(ok, t_near, np.inf)
    axis = lo.argmax(axis=1)
    rows = np.arange(len(d))
    sign = -np.sign(dl[rows, axis])
    normal_l = np.zeros_like(dl)
    normal_l[rows, axis] = sign
    p_l = ol[None, :] + np.where(np.isfinite(t), t, 0.0)[:, None] * dl
    # texture coordinates: the two local coordinates orthogonal to the hit face's axis
    others = np.stack([(axis + 1) % 3, (axis + 2) % 3], axis=1)
    uv = np.take_along_axis(p_l, others, axis=1)
    return t, normal_l @ rot.T, uv


def ray_cast(origin: np.ndarray, directions: np.ndarray, primitives: Sequence[Rect | Box]):
    """Nearest hits of rays from `origin` [3] along `directions` [N, 3] (any length).

    Returns t [N] (ray parameter, inf = no hit), unit world normals [N, 3] facing the
    ray, colours [N, 3] in [0, 1] (texture x Lambert shading)."""
    o = np.asarray(origin, np.float64)
    d = np.asarray(directions, np.float64)
    best = np.full(len(d), np.inf)
    normal = np.zeros_like(d)
    color = np.zeros_like(d)
    for prim in primitives:
        t, n, uv = (_hit_rect if isinstance(prim, Rect) else _hit_box)(o, d, prim)
        closer = t < best
        if not closer.any():
            continue
        best = np.where(closer, t, best)
        normal[closer] = n[closer]
        color[closer] = _texture(uv[closer], np.asarray(prim.color, np.float64), prim.freq)
    # normals face the camera (a plane seen from behind shows its back)
    flip = np.sum(normal * d, axis=1) > 0
    normal[flip] *= -1
    light = np.array([0.3, -0.8, -0.5]) / np.linalg.norm([0.3, -0.8, -0.5])
    lambert = 0.55 + 0.45 * np.clip(-(normal @ light), 0.0, 1.0)
    color *= lambert[:, None]
    return best, normal, color


def render(extrinsic: np.ndarray, intrinsic: np.ndarray, height: int, width: int,
           primitives: Sequence[Rect | Box]):
    """One frame: extrinsic [3, 4] world-to-camera, intrinsic [3, 3] -> image [H, W, 3]
    uint8, depth [H, W] float32 (0 = no hit), points [H, W, 3] float32 (NaN = no hit),
    normals [H, W, 3] float32."""
    r, t = extrinsic[:, :3], extrinsic[:, 3]
    center = -r.T @ t
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)], axis=1)
    rays_cam = pix @ np.linalg.inv(intrinsic).T  # z = 1: the ray parameter is the depth
    rays_world = rays_cam @ r  # R^T applied to each row
    tt, normal, color = ray_cast(center, rays_world, primitives)
    hit = np.isfinite(tt)
    depth = np.where(hit, tt, 0.0)
    pts = center[None, :] + np.where(hit, tt, np.nan)[:, None] * rays_world
    img = np.where(hit[:, None], color, np.array([0.85, 0.9, 0.95]))  # sky colour where nothing is hit
    return ((img * 255.0 + 0.5).astype(np.uint8).reshape(height, width, 3),
            depth.astype(np.float32).reshape(height, width),
            pts.astype(np.float32).reshape(height, width, 3),
            np.where(hit[:, None], normal, 0.0).astype(np.float32).reshape(height, width, 3))


# ---------------------------------------------------------------------------------------
# cameras and scenes
# ---------------------------------------------------------------------------------------


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera [3, 4] (OpenCV) of a camera at `center` [3] looking at `target`
    [3]; `up` is the world direction that appears upwards in the image (y down)."""
    center, target, up = (np.asarray(x, np.float64) for x in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)  # image x = right; with y down, -up points down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return np.concatenate([r, (-r @ center)[:, None]], axis=1)


def orbit_cameras(frames: int, radius: float = 3.0, height: float = -1.0, arc_deg: float = 60.0,
                  target=(0.0, 0.2, 0.0), phase_deg: float = 0.0, jitter: float = 0.0,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """`frames` world-to-camera [S, 3, 4] on a horizontal arc of `arc_deg` degrees at
    `radius` from the y axis, `height` along y (y points down: negative is above the
    floor), all looking at `target`; `jitter` moves each centre by up to that much."""
    angles = np.deg2rad(phase_deg + np.linspace(-arc_deg / 2, arc_deg / 2, frames))
    out = []
    for a in angles:
        c = np.array([radius * np.sin(a), height, -radius * np.cos(a)])
        if jitter and rng is not None:
            c = c + rng.uniform(-jitter, jitter, 3)
        out.append(look_at(c, np.asarray(target, np.float64) + 0.05 * np.array([np.sin(3 * a), 0.0, 0.0])))
    return np.stack(out)


def _rot_y(deg: float) -> tuple:
    a = np.deg2rad(deg)
    m = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return tuple(map(tuple, m))


def room(rng: np.random.Generator, boxes: int = 3) -> tuple:
    """A floor, three walls and `boxes` randomly placed, rotated boxes (world y down,
    the floor at y = 1)."""
    hue = lambda: tuple(rng.uniform(0.3, 1.0, 3))  # noqa: E731
    prims: list = [
        Rect((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (3.0, 3.0), hue(), 2.0),   # floor
        Rect((0.0, -0.5, 2.5), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (3.0, 1.5), hue(), 3.0),  # back wall
        Rect((-2.5, -0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (3.0, 1.5), hue(), 3.0),  # left wall
        Rect((2.5, -0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (3.0, 1.5), hue(), 3.0),  # right wall
    ]
    for _ in range(boxes):
        half = tuple(rng.uniform(0.2, 0.45, 3))
        c = (rng.uniform(-1.2, 1.2), 1.0 - half[1], rng.uniform(-0.6, 1.4))
        prims.append(Box(c, _rot_y(rng.uniform(0, 90)), half, hue(), 5.0))
    return tuple(prims)


def make_scene(frames: int = 6, height: int = 60, width: int = 80, seed: int = 0, *,
               focal: float | tuple[float, float] | None = None,
               name: str | None = None, arc_deg: float = 50.0, radius: float = 3.2, boxes: int = 3,
               jitter: float = 0.05) -> SyntheticScene:
    """A procedural room (`room`) seen by `frames` cameras on an arc (`orbit_cameras`)
    with focal length `focal` pixels (default 0.9 x width; a pair = (fx, fy)) and the
    principal point at the image centre (width/2, height/2). Deterministic in `seed`."""
    if frames < 1 or height < 2 or width < 2:
        raise ValueError(f"need frames >= 1 and an image of at least 2x2 pixels; got {frames}, {width}x{height}")
    rng = np.random.default_rng(seed)
    prims = room(rng, boxes)
    fx, fy = np.broadcast_to(np.asarray(0.9 * width if focal is None else focal, np.float64), (2,))
    k = np.array([[fx, 0.0, width / 2.0], [0.0, fy, height / 2.0], [0.0, 0.0, 1.0]])
    ext = orbit_cameras(frames, radius=radius, height=rng.uniform(-0.6, -0.2), arc_deg=arc_deg,
                        phase_deg=rng.uniform(-20, 20), jitter=jitter, rng=rng)
    outs = [render(e, k, height, width, prims) for e in ext]
    imgs, depth, pts, nrm = (np.stack(x) for x in zip(*outs))
    return SyntheticScene(name=name or f"synthetic_{seed:03d}", images=imgs, depth=depth, points=pts, normals=nrm,
                          extrinsics=ext, intrinsics=np.repeat(k[None], frames, axis=0), primitives=prims)


def write_scene(scene: SyntheticScene, fmt: str, root: str | Path) -> Path:
    """Store `scene` under `root` in the on-disk format `fmt` (a name of
    `rvggt_jax.eval.datasets.FORMATS`: 7scenes, nrgbd, scannet, tnt, dtu, folder, co3d);
    returns the scene's folder."""
    from rvggt_jax.eval.datasets import get_format

    return get_format(fmt).write(scene, Path(root))
