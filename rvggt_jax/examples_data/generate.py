"""Regenerate the bundled example data.

`scene/`: the demo's scene (`rvggt demo`), a held-out procedural room
(`rvggt_jax.synthetic.make_scene(frames=8, height=84, width=112, seed=DEMO_SEED)`, a seed
the shipped rvggt-small never trained on) in the evaluation's "folder" format:
images/frame_XXXX.png, cameras.json (exact cameras) and depth/frame_XXXX.npy.

`images/view_*.jpg`: three small views of another ray-cast scene (a checkered ground
plane, two spheres and a box under a sky gradient) that the tests run the pipeline on
with the tiny random-weight model; they exercise the pipeline, not a model's accuracy.

    python -m rvggt_jax.examples_data.generate
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

WIDTH, HEIGHT, FOCAL = 160, 120, 150.0
N_VIEWS = 3
HERE = Path(__file__).resolve().parent
DEMO_SEED = 7  # in rvggt_jax.synthetic.HELD_OUT_SEEDS
DEMO_FRAMES, DEMO_HW = 8, (84, 112)


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes: x right, y down, z forward), world z is up."""
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    return np.stack([right, down, fwd], axis=1)


def _texture(p: np.ndarray, rng_table: np.ndarray) -> np.ndarray:
    """Checker + hashed value noise on the ground plane (x, y) -> RGB in [0, 1]."""
    cx = np.floor(p[..., 0] * 2.0).astype(int)
    cy = np.floor(p[..., 1] * 2.0).astype(int)
    checker = ((cx + cy) & 1).astype(np.float64)
    fx = np.floor(p[..., 0] * 8.0).astype(int) % 64
    fy = np.floor(p[..., 1] * 8.0).astype(int) % 64
    noise = rng_table[fx, fy]
    base = np.stack([0.55 + 0.3 * checker, 0.45 + 0.25 * checker, 0.3 + 0.1 * checker], axis=-1)
    return np.clip(base * (0.75 + 0.5 * noise[..., None]), 0.0, 1.0)


def render(eye: np.ndarray, target: np.ndarray, rng_table: np.ndarray) -> np.ndarray:
    """`[HEIGHT, WIDTH, 3]` uint8 image seen from `eye` looking at `target`."""
    R = _look_at(eye, target)
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    d_cam = np.stack([(u - WIDTH / 2) / FOCAL, (v - HEIGHT / 2) / FOCAL, np.ones_like(u)], axis=-1)
    d = d_cam @ R.T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)

    t_best = np.full(u.shape, np.inf)
    color = np.zeros(u.shape + (3,))
    sky = np.clip(0.55 + 0.45 * d[..., 2:3], 0, 1) * np.array([0.55, 0.7, 1.0])
    color[:] = sky

    # ground z = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -eye[2] / d[..., 2]
    hit = (t > 0) & np.isfinite(t)
    p = eye + t[..., None] * d
    tex = _texture(p, rng_table)
    upd = hit & (t < t_best)
    t_best = np.where(upd, t, t_best)
    color[upd] = tex[upd]

    light = np.array([0.4, -0.3, 0.85])
    light /= np.linalg.norm(light)
    for centre, radius, rgb in (
        (np.array([0.0, 0.0, 0.6]), 0.6, np.array([0.85, 0.2, 0.15])),
        (np.array([1.3, 0.8, 0.35]), 0.35, np.array([0.2, 0.45, 0.9])),
    ):
        oc = eye - centre
        b = (d * oc).sum(-1)
        c = (oc * oc).sum() - radius**2
        disc = b * b - c
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        upd = (disc > 0) & (t > 0) & (t < t_best)
        n = (eye + t[..., None] * d - centre) / radius
        stripes = 0.75 + 0.25 * np.sign(np.sin(8.0 * np.arctan2(n[..., 1], n[..., 0])))
        shade = (0.3 + 0.7 * np.clip(n @ light, 0, 1)) * stripes
        color[upd] = (rgb * shade[..., None])[upd]
        t_best = np.where(upd, t, t_best)

    # axis-aligned box
    lo, hi = np.array([-1.6, -1.0, 0.0]), np.array([-0.9, -0.3, 0.9])
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - eye) / d
        t1 = (hi - eye) / d
    tmin = np.minimum(t0, t1).max(-1)
    tmax = np.maximum(t0, t1).min(-1)
    upd = (tmax > np.maximum(tmin, 0)) & (tmin > 0) & (tmin < t_best)
    p = eye + tmin[..., None] * d
    face = np.argmin(np.minimum(np.abs(p - lo), np.abs(p - hi)), axis=-1)
    grid = ((np.floor(p[..., 0] * 6) + np.floor(p[..., 1] * 6) + np.floor(p[..., 2] * 6)).astype(int) & 1)
    shade = np.array([0.7, 0.85, 1.0])[face] * (0.8 + 0.2 * grid)
    color[upd] = (np.array([0.25, 0.7, 0.3]) * shade[..., None])[upd]

    return (np.clip(color, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_demo_scene(root: Path = HERE) -> Path:
    """ROOT/scene: the demo's held-out scene with its ground truth (no points.ply)."""
    import shutil

    from rvggt_jax.synthetic import HELD_OUT_SEEDS, make_scene, write_scene

    assert DEMO_SEED in HELD_OUT_SEEDS
    scene = make_scene(frames=DEMO_FRAMES, height=DEMO_HW[0], width=DEMO_HW[1], seed=DEMO_SEED, name="scene")
    if (root / "scene").exists():
        shutil.rmtree(root / "scene")
    d = write_scene(scene, "folder", root)
    (d / "points.ply").unlink()
    return d


def main() -> None:
    write_demo_scene()
    rng = np.random.default_rng(0)
    table = rng.random((64, 64))
    out = HERE / "images"
    out.mkdir(exist_ok=True)
    target = np.array([0.0, 0.0, 0.4])
    for i, angle in enumerate(np.linspace(-0.5, 0.5, N_VIEWS)):
        eye = np.array([5.0 * np.cos(angle - np.pi / 2), 5.0 * np.sin(angle - np.pi / 2), 2.2])
        Image.fromarray(render(eye, target, table)).save(out / f"view_{i:02d}.jpg", quality=85)


if __name__ == "__main__":
    main()
