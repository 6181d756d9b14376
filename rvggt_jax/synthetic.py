"""Procedural scenes with exact ground truth: textured planes, boxes, spheres and cylinders seen by known
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

`random_scene(seed, frames, ...)` is the training data's family (`rvggt_jax.train.procedural`):
boxes, spheres and cylinders with checker, noise or stripe textures, a random light and
focal length, seen along an orbit, a forward walk or from scattered look-at cameras.

`loop_walkthrough(frames, ...)` is a long walk around a closed corridor that returns to
its start (for the long-sequence pipeline, `rvggt_jax.sequence`): it holds only the
cameras and the primitives, and renders any subset of frames on demand.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["Box", "Cylinder", "HELD_OUT_SEEDS", "LoopWalk", "PATHS", "Rect", "Sphere", "SyntheticScene", "TEXTURES",
           "camera_centers", "forward_cameras", "look_at", "lookat_cameras", "loop_walkthrough", "make_scene",
           "orbit_cameras", "random_room", "random_scene", "ray_cast", "render", "write_scene"]


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
    texture: str = "checker"


@dataclasses.dataclass(frozen=True)
class Box:
    """A textured box: centre [3], rotation [3, 3] (columns = the box axes in the
    world), half extents [3]."""

    center: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]
    half: tuple[float, float, float]
    color: tuple[float, float, float]
    freq: float = 6.0
    texture: str = "checker"


@dataclasses.dataclass(frozen=True)
class Sphere:
    """A textured sphere: centre [3], radius."""

    center: tuple[float, float, float]
    radius: float
    color: tuple[float, float, float]
    freq: float = 3.0
    texture: str = "checker"


@dataclasses.dataclass(frozen=True)
class Cylinder:
    """A textured upright cylinder with caps: centre [3], radius, half height (along the
    world y axis)."""

    center: tuple[float, float, float]
    radius: float
    half_height: float
    color: tuple[float, float, float]
    freq: float = 4.0
    texture: str = "checker"


TEXTURES = ("checker", "noise", "stripes")
"""Surface patterns: a checkerboard times a ripple (the original scenes'), two octaves of
value noise, and slanted stripes times a ripple. Each makes every patch of a surface
distinct enough to match."""


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


def _hash(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random value in [0, 1) per integer lattice point."""
    v = np.sin(ix * 127.1 + iy * 311.7) * 43758.5453
    return v - np.floor(v)


def _value_noise(uv: np.ndarray) -> np.ndarray:
    """Bilinear value noise [N] in [0, 1) of coordinates uv [N, 2] (one lattice cell per unit)."""
    i = np.floor(uv)
    f = uv - i
    f = f * f * (3.0 - 2.0 * f)  # smoothstep: no creases along the lattice lines
    a, b = _hash(i[:, 0], i[:, 1]), _hash(i[:, 0] + 1, i[:, 1])
    c, d = _hash(i[:, 0], i[:, 1] + 1), _hash(i[:, 0] + 1, i[:, 1] + 1)
    return (a + (b - a) * f[:, 0]) * (1 - f[:, 1]) + (c + (d - c) * f[:, 0]) * f[:, 1]


def _texture(uv: np.ndarray, color: np.ndarray, freq: float, kind: str = "checker") -> np.ndarray:
    """Colour [N, 3] in [0, 1] of surface coordinates uv [N, 2] for a pattern of
    `TEXTURES`."""
    ripple = 0.5 + 0.5 * np.sin(7.3 * uv[:, 0] + 3.1 * np.cos(5.7 * uv[:, 1]))
    if kind == "checker":
        checker = (np.floor(uv[:, 0] * freq) + np.floor(uv[:, 1] * freq)) % 2
        shade = 0.45 + 0.35 * checker + 0.2 * ripple
    elif kind == "noise":
        shade = 0.3 + 0.45 * _value_noise(uv * freq) + 0.25 * _value_noise(uv * freq * 2.7 + 17.0)
    elif kind == "stripes":
        stripe = (np.floor((uv[:, 0] + 0.6 * uv[:, 1]) * freq) % 2)
        shade = 0.4 + 0.35 * stripe + 0.25 * ripple
    else:
        raise ValueError(f"unknown texture {kind!r}; known: {', '.join(TEXTURES)}")
    return np.clip(color[None, :] * shade[:, None], 0.0, 1.0)


def _hit_rect(o: np.ndarray, d: np.ndarray, r: Rect):
    c, u, v = (np.asarray(x, np.float64) for x in (r.center, r.u, r.v))
    # u x v written out: np.cross's axis handling costs more than a small frame's rays
    n = np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])
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


def _hit_sphere(o: np.ndarray, d: np.ndarray, sp: Sphere):
    c = np.asarray(sp.center, np.float64)
    oc = o - c
    a = np.einsum("ij,ij->i", d, d)
    b = 2.0 * (d @ oc)
    disc = b * b - 4.0 * a * (oc @ oc - sp.radius ** 2)
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2.0 * a)  # the near root: cameras are outside every sphere
    ok = (disc >= 0) & (t > 1e-6)
    t = np.where(ok, t, np.inf)
    n = (o[None, :] + np.where(ok, t, 0.0)[:, None] * d - c) / sp.radius
    # texture coordinates: arc lengths along the azimuth and the polar angle
    uv = sp.radius * np.stack([np.arctan2(n[:, 0], n[:, 2]), np.arcsin(np.clip(n[:, 1], -1, 1))], axis=1)
    return t, n, uv


def _hit_cylinder(o: np.ndarray, d: np.ndarray, cy: Cylinder):
    c = np.asarray(cy.center, np.float64)
    ox, oy, oz = o - c
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    a = dx * dx + dz * dz
    b = 2.0 * (ox * dx + oz * dz)
    disc = b * b - 4.0 * a * (ox * ox + oz * oz - cy.radius ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        t_side = (-b - np.sqrt(disc)) / (2.0 * a)
        y_side = oy + t_side * dy
        side_ok = (disc >= 0) & (a > 1e-12) & (t_side > 1e-6) & (np.abs(y_side) <= cy.half_height)
        t_side = np.where(side_ok, t_side, np.inf)
        # the cap facing the camera: y = -h when the camera is above it (y points down), else +h
        cap_y = -cy.half_height if oy < 0 else cy.half_height
        t_cap = (cap_y - oy) / dy
        px, pz = ox + t_cap * dx, oz + t_cap * dz
        cap_ok = np.isfinite(t_cap) & (t_cap > 1e-6) & (px * px + pz * pz <= cy.radius ** 2)
    t_cap = np.where(cap_ok, t_cap, np.inf)
    on_cap = t_cap < t_side
    t = np.minimum(t_side, t_cap)
    tt = np.where(np.isfinite(t), t, 0.0)
    hx, hy, hz = ox + tt * dx, oy + tt * dy, oz + tt * dz
    n = np.where(on_cap[:, None], np.array([0.0, np.sign(cap_y), 0.0]),
                 np.stack([hx, np.zeros_like(hx), hz], axis=1) / cy.radius)
    uv = np.where(on_cap[:, None], np.stack([hx, hz], axis=1),
                  np.stack([cy.radius * np.arctan2(hx, hz), hy], axis=1))
    return t, n, uv


_HITS = {Rect: _hit_rect, Box: _hit_box, Sphere: _hit_sphere, Cylinder: _hit_cylinder}

DEFAULT_LIGHT = (0.3, -0.8, -0.5)
"""The direction light travels in (world, y down: from above, in front, to the right)."""


def ray_cast(origin: np.ndarray, directions: np.ndarray, primitives: Sequence[Rect | Box | Sphere | Cylinder],
             light: Sequence[float] = DEFAULT_LIGHT):
    """Nearest hits of rays from `origin` [3] along `directions` [N, 3] (any length).

    Returns t [N] (ray parameter, inf = no hit), unit world normals [N, 3] facing the
    ray, colours [N, 3] in [0, 1] (texture x Lambert shading of a light travelling along
    `light` [3], plus ambient)."""
    o = np.asarray(origin, np.float64)
    d = np.asarray(directions, np.float64)
    best = np.full(len(d), np.inf)
    normal = np.zeros_like(d)
    color = np.zeros_like(d)
    for prim in primitives:
        t, n, uv = _HITS[type(prim)](o, d, prim)
        closer = t < best
        if not closer.any():
            continue
        best = np.where(closer, t, best)
        normal[closer] = n[closer]
        color[closer] = _texture(uv[closer], np.asarray(prim.color, np.float64), prim.freq, prim.texture)
    # normals face the camera (a plane seen from behind shows its back)
    flip = np.sum(normal * d, axis=1) > 0
    normal[flip] *= -1
    light = np.asarray(light, np.float64) / np.linalg.norm(light)
    lambert = 0.55 + 0.45 * np.clip(-(normal @ light), 0.0, 1.0)
    color *= lambert[:, None]
    return best, normal, color


def render(extrinsic: np.ndarray, intrinsic: np.ndarray, height: int, width: int,
           primitives: Sequence[Rect | Box | Sphere | Cylinder], light: Sequence[float] = DEFAULT_LIGHT):
    """One frame: extrinsic [3, 4] world-to-camera, intrinsic [3, 3] -> image [H, W, 3]
    uint8, depth [H, W] float32 (0 = no hit), points [H, W, 3] float32 (NaN = no hit),
    normals [H, W, 3] float32."""
    r, t = extrinsic[:, :3], extrinsic[:, 3]
    center = -r.T @ t
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)], axis=1)
    rays_cam = pix @ np.linalg.inv(intrinsic).T  # z = 1: the ray parameter is the depth
    rays_world = rays_cam @ r  # R^T applied to each row
    tt, normal, color = ray_cast(center, rays_world, primitives, light)
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


def camera_centers(extrinsics: np.ndarray) -> np.ndarray:
    """Camera centres [S, 3] = -R^T t of world-to-camera extrinsics [S, 3, 4]."""
    e = np.asarray(extrinsics, dtype=np.float64)
    return -np.einsum("sji,sj->si", e[:, :, :3], e[:, :, 3])


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


# ---------------------------------------------------------------------------------------
# varied scenes for training: more primitives, textures, lights and camera paths
# ---------------------------------------------------------------------------------------

PATHS = ("orbit", "forward", "lookat")
"""Camera paths of `random_scene`: an arc around the room's middle (`orbit_cameras`), a
walk forward into the room (`forward_cameras`), cameras scattered over the room looking
at random points of its middle (`lookat_cameras`, large baselines)."""

HELD_OUT_SEEDS = range(0, 100_000)
"""Seeds kept for evaluation: the shipped small model never trained on `make_scene` or
`random_scene` with these seeds (`rvggt_jax.train.procedural` draws from 100000 up)."""


def _color(rng: np.random.Generator) -> tuple:
    return tuple(float(x) for x in rng.uniform(0.25, 1.0, 3))


def random_room(rng: np.random.Generator, objects: int | None = None) -> tuple:
    """A room like `room` (floor at y = 1, back and side walls), its size, textures and
    colours drawn, holding `objects` (default 2 to 6) boxes, spheres and cylinders
    resting on the floor within x, z in [-1.3, 1.3] x [-0.7, 1.5]. Every object's top is
    below y = 0.1, so a camera with y <= -0.1 inside the walls is inside no object."""
    tex = lambda: TEXTURES[int(rng.integers(len(TEXTURES)))]  # noqa: E731
    half_w, depth_back = rng.uniform(2.3, 3.0), rng.uniform(2.2, 3.2)
    prims: list = [
        Rect((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (half_w + 0.5, 3.5), _color(rng),
             float(rng.uniform(1.0, 3.0)), tex()),
        Rect((0.0, -0.5, depth_back), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (half_w + 0.5, 1.5), _color(rng),
             float(rng.uniform(1.5, 4.0)), tex()),
        Rect((-half_w, -0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (3.5, 1.5), _color(rng),
             float(rng.uniform(1.5, 4.0)), tex()),
        Rect((half_w, -0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (3.5, 1.5), _color(rng),
             float(rng.uniform(1.5, 4.0)), tex()),
    ]
    n = int(rng.integers(2, 7)) if objects is None else int(objects)
    for _ in range(n):
        kind = rng.choice(["box", "sphere", "cylinder"])
        x, z = rng.uniform(-1.3, 1.3), rng.uniform(-0.7, 1.5)
        freq = float(rng.uniform(3.0, 8.0))
        if kind == "box":
            half = tuple(float(v) for v in rng.uniform(0.15, 0.45, 3))
            prims.append(Box((x, 1.0 - half[1], z), _rot_y(rng.uniform(0, 90)), half, _color(rng), freq, tex()))
        elif kind == "sphere":
            r = float(rng.uniform(0.15, 0.45))
            prims.append(Sphere((x, 1.0 - r, z), r, _color(rng), freq, tex()))
        else:
            r, h = float(rng.uniform(0.12, 0.35)), float(rng.uniform(0.15, 0.45))
            prims.append(Cylinder((x, 1.0 - h, z), r, h, _color(rng), freq, tex()))
    return tuple(prims)


def forward_cameras(frames: int, rng: np.random.Generator) -> np.ndarray:
    """`frames` world-to-camera [S, 3, 4] walking forward (+z) into the room: from z in
    [-3.2, -2.2] over 0.4 to 1.6 m, sideways drift, a slowly turning heading (up to 15
    degrees either way) pitched down 5 to 25 degrees."""
    start = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-0.9, -0.25), rng.uniform(-3.2, -2.2)])
    dist, drift = rng.uniform(0.4, 1.6), rng.uniform(-0.4, 0.4)
    yaw0, yaw1 = np.deg2rad(rng.uniform(-15, 15, 2))
    pitch = np.deg2rad(rng.uniform(5, 25))
    out = []
    for f in np.linspace(0.0, 1.0, frames):
        c = start + np.array([drift * f, 0.0, dist * f])
        yaw = yaw0 + (yaw1 - yaw0) * f
        look = np.array([np.sin(yaw), np.tan(pitch), np.cos(yaw)])
        out.append(look_at(c, c + look))
    return np.stack(out)


def lookat_cameras(frames: int, rng: np.random.Generator) -> np.ndarray:
    """`frames` world-to-camera [S, 3, 4] at random places in front of and over the room
    (x in [-2, 2], y in [-1.3, -0.2], z in [-3.2, 0.3]), each looking at a random point of
    the room's middle: baselines of metres between any two frames."""
    out = []
    while len(out) < frames:
        c = np.array([rng.uniform(-2.0, 2.0), rng.uniform(-1.3, -0.2), rng.uniform(-3.2, 0.3)])
        t = np.array([rng.uniform(-0.8, 0.8), rng.uniform(0.2, 0.9), rng.uniform(-0.2, 1.4)])
        if np.linalg.norm(t - c) >= 1.0:
            out.append(look_at(c, t))
    return np.stack(out)


def random_scene(seed: int, frames: int | None = None, height: int = 60, width: int = 80, *,
                 path: str | None = None, name: str | None = None) -> SyntheticScene:
    """A varied scene for training, deterministic in `seed`: a `random_room`, a random
    light, a focal length of 0.7 to 1.2 x width, and `frames` cameras (default 2 to 24,
    drawn) on a path of `PATHS` (default drawn: orbit 1/2, forward 1/4, lookat 1/4).
    Orbits vary `make_scene`'s: radius 2.4 to 3.4, arcs of 20 to 90 degrees kept inside
    the side walls."""
    rng = np.random.default_rng([int(seed), 0x5CE7E])  # a stream of its own: not make_scene's for the same seed
    n = int(rng.integers(2, 25)) if frames is None else int(frames)
    if n < 1 or height < 2 or width < 2:
        raise ValueError(f"need frames >= 1 and an image of at least 2x2 pixels; got {n}, {width}x{height}")
    kind = path or str(rng.choice(PATHS, p=[0.5, 0.25, 0.25]))
    if kind not in PATHS:
        raise ValueError(f"unknown camera path {kind!r}; known: {', '.join(PATHS)}")
    prims = random_room(rng)
    light = np.array([rng.uniform(-0.6, 0.6), -1.0, rng.uniform(-0.8, 0.3)])
    f = float(rng.uniform(0.7, 1.2)) * width
    k = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    if kind == "orbit":
        radius = float(rng.uniform(2.4, 3.4))
        # keep |x| = radius sin(angle) < 2.2 so every camera stays between the side walls
        max_half = min(45.0, float(np.rad2deg(np.arcsin(min(1.0, 2.2 / radius)))))
        arc = float(rng.uniform(20.0, 2 * max_half - 10.0))
        phase = float(rng.uniform(-(max_half - arc / 2), max_half - arc / 2))
        ext = orbit_cameras(n, radius=radius, height=float(rng.uniform(-0.9, -0.15)), arc_deg=arc,
                            target=(float(rng.uniform(-0.3, 0.3)), float(rng.uniform(0.0, 0.5)),
                                    float(rng.uniform(-0.2, 0.6))),
                            phase_deg=phase, jitter=0.05, rng=rng)
    elif kind == "forward":
        ext = forward_cameras(n, rng)
    else:
        ext = lookat_cameras(n, rng)
    outs = [render(e, k, height, width, prims, light) for e in ext]
    imgs, depth, pts, nrm = (np.stack(x) for x in zip(*outs))
    return SyntheticScene(name=name or f"random_{kind}_{seed}", images=imgs, depth=depth, points=pts, normals=nrm,
                          extrinsics=ext, intrinsics=np.repeat(k[None], n, axis=0), primitives=prims)


def write_scene(scene: SyntheticScene, fmt: str, root: str | Path) -> Path:
    """Store `scene` under `root` in the on-disk format `fmt` (a name of
    `rvggt_jax.eval.datasets.FORMATS`: 7scenes, nrgbd, scannet, tnt, dtu, folder, co3d);
    returns the scene's folder."""
    from rvggt_jax.eval.datasets import get_format

    return get_format(fmt).write(scene, Path(root))


# ---------------------------------------------------------------------------------------
# a long walk around a loop
# ---------------------------------------------------------------------------------------


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
