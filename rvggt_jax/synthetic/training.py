"""Varied scenes for training (`rvggt_jax.train.procedural`): `random_room` with boxes,
spheres and cylinders in three textures, a random light and focal length, seen along an
orbit, a forward walk or from scattered look-at cameras (`random_scene`). Seeds in
`HELD_OUT_SEEDS` are kept for evaluation."""

from __future__ import annotations

import numpy as np

from rvggt_jax.synthetic.render import TEXTURES, Box, Cylinder, Rect, Sphere, render
from rvggt_jax.synthetic.scenes import SyntheticScene, _rot_y, look_at, orbit_cameras

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
