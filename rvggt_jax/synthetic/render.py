"""Ray casting of textured primitives in numpy: rectangles, boxes, spheres and upright
cylinders, with checker, value-noise or stripe textures under a Lambert light
(`ray_cast`), and one pinhole frame of them (`render`: colours, depth, world points,
normals)."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

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
