"""Procedural training data, streamed from seeds: nothing is stored, and step i's batch is
a function of (run seed, i) alone, so a resumed run draws exactly the batches the
uninterrupted one drew.

A scene is one of two families (`procedural_scene`):
- 1 in 3: `rvggt_jax.synthetic.make_scene`, the evaluation's room on an arc (its arc
  and box count drawn), so the held-out evaluation scenes come from a family the model saw;
- 2 in 3: `rvggt_jax.synthetic.random_scene`: boxes, spheres and cylinders, three
  textures, a random light and focal length, orbit / forward / look-at camera paths.

Scene seeds start at `TRAIN_SEED_BASE`; `rvggt_jax.synthetic.HELD_OUT_SEEDS` (below it)
are never drawn, and are the evaluation's.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from rvggt_jax.synthetic import HELD_OUT_SEEDS, make_scene, random_scene
from rvggt_jax.train import data as data_mod

TRAIN_SEED_BASE = HELD_OUT_SEEDS.stop
"""The first scene seed training draws; every seed below it is held out."""


def scene_seed(run_seed: int, step: int, index: int) -> int:
    """The scene seed of scene `index` of step `step`'s batch: >= TRAIN_SEED_BASE, from a
    hash of the three (so two runs with different seeds see different scenes)."""
    h = np.random.default_rng([int(run_seed), int(step), int(index), 0xDA7A]).integers(0, 2 ** 40)
    return TRAIN_SEED_BASE + int(h)


def procedural_scene(seed: int, frames: int, size: tuple[int, int]):
    """The training scene of `seed` (>= TRAIN_SEED_BASE) with `frames` frames rendered at
    `size` (H, W): a `SyntheticScene`."""
    if int(seed) < TRAIN_SEED_BASE:
        raise ValueError(f"scene seeds below {TRAIN_SEED_BASE} are held out for evaluation; got {seed}")
    h, w = size
    rng = np.random.default_rng([int(seed), 0xFA11])
    if rng.uniform() < 1 / 3:
        return make_scene(frames=frames, height=h, width=w, seed=int(seed), arc_deg=float(rng.uniform(25.0, 80.0)),
                          boxes=int(rng.integers(2, 5)))
    return random_scene(int(seed), frames, h, w)


def procedural_example(seed: int, frames: int, size: tuple[int, int], tracks: int = 0) -> data_mod.Example:
    """One normalised training example (`rvggt_jax.train.data.make_example`) of the scene
    of `seed`, rendered at the network size, with `tracks` ground-truth tracks
    (`exact_tracks`) when > 0."""
    h, w = data_mod._check_size(size)
    sc = procedural_scene(seed, frames, (h, w))
    ex = data_mod.make_example(sc.images, sc.extrinsics, sc.intrinsics, sc.depth)
    if tracks > 0:
        ex["tracks"], ex["track_vis"] = exact_tracks(ex, tracks, np.random.default_rng([int(seed), 0x7AC5]))
    return ex


def exact_tracks(ex: data_mod.Example, n: int, rng: np.random.Generator, rel_tol: float = 0.03
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth tracks of an example: n query pixels drawn among frame 0's pixels with
    depth, their world points projected into every frame. Returns tracks [S, n, 2] (x, y
    network pixels, integer = pixel centre) and visibility [S, n] (1: in the image, in
    front of the camera, and not hidden: the frame's depth at the nearest pixel within
    `rel_tol` of the projected depth). A frame 0 with fewer than n such pixels repeats
    them (a frame 0 with none: every track invisible)."""
    depth, mask = ex["depth"], ex["point_mask"]
    s, h, w = depth.shape
    valid = np.flatnonzero(mask[0])
    if valid.size == 0:
        return np.zeros((s, n, 2), np.float32), np.zeros((s, n), np.float32)
    pick = rng.choice(valid, n, replace=valid.size < n)
    world = ex["world_points"][0].reshape(-1, 3)[pick].astype(np.float64)  # [n, 3]
    ext, k = ex["extrinsics"].astype(np.float64), ex["intrinsics"].astype(np.float64)
    cam = np.einsum("sij,nj->sni", ext[:, :, :3], world) + ext[:, None, :, 3]  # [S, n, 3]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.einsum("sij,snj->sni", k[:, :2, :], cam / z[..., None])  # [S, n, 2]
    col, row = np.round(uv[..., 0]), np.round(uv[..., 1])
    inside = (z > 1e-6) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    ci, ri = np.clip(col, 0, w - 1).astype(int), np.clip(row, 0, h - 1).astype(int)
    seen = depth[np.arange(s)[:, None], ri, ci]
    vis = inside & (seen > 0) & (np.abs(seen - z) <= rel_tol * z)
    # frame 0: the query pixel itself (its own depth, exactly)
    q = np.stack([pick % w, pick // w], axis=1).astype(np.float64)
    uv[0], vis[0] = q, True
    uv = np.where(np.isfinite(uv), uv, 0.0)
    return uv.astype(np.float32), vis.astype(np.float32)


def procedural_batch(step: int, seed: int, batch: int, frames: int | tuple[int, int], size: tuple[int, int],
                     buckets: Sequence[int] | None = None, tracks: int = 0) -> data_mod.Example:
    """Step `step`'s batch: `batch` scenes with one frame count drawn in `frames` and
    rounded down to a bucket (`rvggt_jax.train.data.frame_plan`), every key [B, S, ...]."""
    lo, hi, bs = data_mod.frame_plan(frames, buckets)
    n = int(data_mod.step_rng(seed, step).integers(lo, hi + 1))
    s = max(b for b in bs if b <= n)
    return data_mod.stack([procedural_example(scene_seed(seed, step, j), s, size, tracks) for j in range(batch)])
