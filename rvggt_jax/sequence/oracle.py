"""A stand-in for a trained model: `OraclePredictor` predicts any set of frames of a
`rvggt_jax.synthetic.LoopWalk` from the walk's true geometry, with the errors that make
chunked reconstruction hard.

    walk = loop_walkthrough(1200)
    oracle = OraclePredictor(walk, noise=0.01, bias_deg=0.3)
    chunk = oracle(range(0, 60))          # a ChunkPrediction of 60 frames
    chunks = [oracle(f) for f in plan_chunks(1200, 60, 10)]
    trajectory = align_chunks(chunks, loop_closure=True, verify=oracle)

What each call gets wrong, as a feed-forward model does:

- its own frame and scale: the first given frame's camera is the origin, and the whole
  prediction is multiplied by a random scale;
- pixel noise: each point moves (isotropic Gaussian) by `noise` x its depth x a
  per-pixel factor (log-normal), and the confidence is lower where that factor is larger; optionally a fraction
  `outliers` of the pixels is far off and as confident as the rest;
- a rotation bias: the call's geometry bends, frame j of F (cameras and points) rotated
  about the first camera by `bias_deg` x j / (F - 1) degrees. A rotation of a chunk as a
  whole would be undone by the Sim(3) alignment on shared frames; a bend is not: each
  chunk's last frames, those the next chunk is aligned on, are turned by ~`bias_deg`,
  and the chained trajectory drifts by that much per chunk.

Every random draw is seeded by the frames asked for (and `seed`), so the same call gives
the same prediction. Descriptors simulate place recognition: random Fourier features of
the true camera centre and viewing direction (cosine similarity ~ exp(-d^2 / 2) for a
distance d in units of `place_scale` metres and `heading_scale` of the unit viewing
vector), with noise, seeded per frame: one frame has one descriptor whichever call
predicts it.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Sequence

import numpy as np

from rvggt_jax.errors import InputError
from rvggt_jax.sequence.prediction import ChunkPrediction
from rvggt_jax.sequence.sim3 import Sim3
from rvggt_jax.synthetic import LoopWalk

__all__ = ["OraclePredictor", "axis_angle"]


def axis_angle(axis, angle: float) -> np.ndarray:
    """[3, 3] rotation by `angle` radians about `axis` [3] (any length > 0), Rodrigues."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


class OraclePredictor:
    """frames [F] -> ChunkPrediction of those frames of `walk`; usable both as the
    per-chunk predictor and as the loop verifier (`verify`).

    noise        pixel noise, a fraction of the depth (0: exact points)
    bias_deg     the bend of each call, degrees over its F frames (0: none)
    bias_axis    the bend's axis [3] in the first camera's axes (default its y axis, the
                 image's down direction, about vertical: a heading bias, the walk turning
                 a little more than it does); None: a random axis per call
    scale_range  each call's scale is drawn log-uniformly from this range
    outliers     fraction of the pixels displaced by ~30% of their depth
    descriptor_dim, descriptor_noise, place_scale, heading_scale: the descriptors (D,
                 noise norm relative to the descriptor's, metres, unit-vector length)
    cache_frames the true geometry of up to this many frames is kept (consecutive chunks
                 and loop verifications render the same frames again); 0: none
    """

    def __init__(self, walk: LoopWalk, *, noise: float = 0.01, bias_deg: float = 0.3,
                 bias_axis: Sequence[float] | None = (0.0, 1.0, 0.0), scale_range: tuple[float, float] = (0.5, 2.0),
                 outliers: float = 0.0, descriptor_dim: int = 128, descriptor_noise: float = 0.2,
                 place_scale: float = 2.0, heading_scale: float = 0.5, seed: int = 0, cache_frames: int = 0):
        if noise < 0 or not 0 <= outliers < 1 or not 0 < scale_range[0] <= scale_range[1]:
            raise InputError(f"OraclePredictor needs noise >= 0, 0 <= outliers < 1 and 0 < scale_range[0] <= "
                             f"scale_range[1]; got {noise}, {outliers}, {scale_range}")
        self.walk, self.noise, self.bias_deg, self.outliers = walk, float(noise), float(bias_deg), float(outliers)
        self.bias_axis = None if bias_axis is None else np.asarray(bias_axis, np.float64)
        self.scale_range, self.seed = (float(scale_range[0]), float(scale_range[1])), int(seed)
        self.descriptor_noise, self.cache_frames = float(descriptor_noise), int(cache_frames)
        self._place = np.array([place_scale] * 3 + [heading_scale] * 3, np.float64)
        rng = np.random.default_rng([self.seed, 0x0DE5C])
        self._proj = rng.standard_normal((6, descriptor_dim))
        self._phase = rng.uniform(0.0, 2 * np.pi, descriptor_dim)
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def truth(self, frames: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """World points [F, H, W, 3] float32 (NaN: no surface) and depth [F, H, W] float32
        (0: no surface) of `frames`, rendered (or from the cache)."""
        frames = [int(f) for f in frames]
        got = {}
        missing = [f for f in dict.fromkeys(frames) if f not in self._cache]
        if missing:
            scene = self.walk.render(missing)
            got = {f: (scene.points[i], scene.depth[i]) for i, f in enumerate(missing)}
        for f in dict.fromkeys(frames):
            if f in self._cache:
                got[f] = self._cache[f]
                self._cache.move_to_end(f)
            elif self.cache_frames:
                self._cache[f] = got[f]
        while len(self._cache) > self.cache_frames:
            self._cache.popitem(last=False)
        return np.stack([got[f][0] for f in frames]), np.stack([got[f][1] for f in frames])

    def descriptors(self, frames: Sequence[int]) -> np.ndarray:
        """[F, D] float32 unit place descriptors of `frames` (see the module docstring)."""
        e = self.walk.extrinsics[np.asarray(frames, np.int64)]
        centre = -np.einsum("fji,fj->fi", e[:, :, :3], e[:, :, 3])
        feat = np.concatenate([centre, e[:, 2, :3]], axis=1) / self._place  # row 2 of R: the viewing axis
        d = np.cos(feat @ self._proj + self._phase)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        for i, f in enumerate(frames):
            jitter = np.random.default_rng([self.seed, 1, int(f)]).standard_normal(d.shape[1])
            d[i] += self.descriptor_noise * jitter / np.sqrt(d.shape[1])
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    def world_to_call(self, frames: Sequence[int]) -> list[Sim3]:
        """The transform [F] of each frame's true geometry into the call's frame: the
        scale, the first camera as origin and the bend (see the module docstring)."""
        frames = [int(f) for f in frames]
        rng = np.random.default_rng([self.seed, 2, len(frames), *frames])
        lo, hi = np.log(self.scale_range)
        s = float(np.exp(rng.uniform(lo, hi)))
        axis = self.bias_axis if self.bias_axis is not None else rng.standard_normal(3)
        e0 = self.walk.extrinsics[frames[0]]
        out = []
        for j in range(len(frames)):
            bend = axis_angle(axis, np.deg2rad(self.bias_deg) * j / max(len(frames) - 1, 1))
            out.append(Sim3(s, bend @ e0[:, :3], s * bend @ e0[:, 3]))
        return out

    def __call__(self, frames: Sequence[int]) -> ChunkPrediction:
        """frames [F] -> ChunkPrediction: extrinsics [F, 3, 4], intrinsics [F, 3, 3],
        points [F, H, W, 3] float32 (NaN where no surface), confidence [F, H, W] float32
        (0 where no surface, >= 1 elsewhere), descriptors [F, D], in the call's frame."""
        frames = [int(f) for f in np.asarray(frames).reshape(-1)]
        if not frames or min(frames) < 0 or max(frames) >= len(self.walk):
            raise InputError(f"OraclePredictor: frames must be in [0, {len(self.walk)}); got {frames[:5]}...")
        pts, depth = self.truth(frames)
        rng = np.random.default_rng([self.seed, 3, len(frames), *frames])  # the noise's own stream
        factor = np.exp(0.5 * rng.standard_normal(depth.shape))
        valid = depth > 0
        world = pts.astype(np.float64)
        world += rng.standard_normal(pts.shape) * (self.noise * depth * factor)[..., None]
        if self.outliers:
            far = valid & (rng.random(depth.shape) < self.outliers)
            world[far] += rng.standard_normal((int(far.sum()), 3)) * 0.3 * depth[far][:, None]
        conf = np.where(valid, 1.0 + 1.0 / factor, 0.0).astype(np.float32)
        tf = self.world_to_call(frames)
        points = np.stack([t.apply(w) for t, w in zip(tf, world)]).astype(np.float32)
        ext = np.stack([t.transform_extrinsics(self.walk.extrinsics[f]) for t, f in zip(tf, frames)])
        return ChunkPrediction(frames=np.asarray(frames), extrinsics=ext,
                               intrinsics=np.repeat(self.walk.intrinsics[None], len(frames), axis=0),
                               points=points, confidence=conf, descriptors=self.descriptors(frames))
