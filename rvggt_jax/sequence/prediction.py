"""What the long-sequence pipeline takes and gives: one chunk's prediction in its own
coordinate frame (`ChunkPrediction`), and the whole sequence's cameras in the first
chunk's frame (`Trajectory`). Plain numpy containers: any feed-forward model that
predicts cameras and point maps for a set of frames can fill them.

Conventions (upstream VGGT's): extrinsics are world-to-camera [R | t] with OpenCV axes
(x right, y down, z forward); intrinsics are pinhole matrices in the pixels of the point
maps; a chunk's "world" is its own first camera, up to the chunk's unknown scale.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from rvggt_jax.errors import InputError
from rvggt_jax.sequence.sim3 import Sim3

__all__ = ["ChunkPrediction", "LoopEdge", "Trajectory"]


def _shape(a: Any) -> tuple[int, ...]:
    return tuple(np.shape(a))


@dataclasses.dataclass(frozen=True, eq=False)
class ChunkPrediction:
    """One chunk's output, in the chunk's own coordinate frame.

    frames       [F] int, indices of the chunk's frames in the whole sequence
    extrinsics   [F, 3, 4] world-to-camera, OpenCV axes
    intrinsics   [F, 3, 3] pinhole, in the point maps' pixels
    points       [F, H, W, 3] world points of every pixel (NaN: none)
    confidence   [F, H, W] non-negative; larger is more reliable
    descriptors  [F, D] per-frame place descriptors for loop detection, or None

    `points` and `confidence` may be any array-likes with a shape that index by frame
    (`np.load(..., mmap_mode="r")` arrays): the pipeline reads only the frames it aligns
    on, so a chunk cached on disk is not loaded whole.
    """

    frames: np.ndarray
    extrinsics: np.ndarray
    intrinsics: np.ndarray
    points: Any
    confidence: Any
    descriptors: np.ndarray | None = None

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames)
        if frames.ndim != 1 or len(frames) < 1 or not np.issubdtype(frames.dtype, np.integer):
            raise InputError(f"ChunkPrediction.frames must be [F] ints with F >= 1; got {frames.dtype} "
                             f"{frames.shape}")
        if len(np.unique(frames)) != len(frames):
            raise InputError(f"ChunkPrediction.frames holds a frame twice: {frames.tolist()}")
        object.__setattr__(self, "frames", frames.astype(np.int64))
        f = len(frames)
        expect = {"extrinsics": (f, 3, 4), "intrinsics": (f, 3, 3)}
        for name, shape in expect.items():
            if _shape(getattr(self, name)) != shape:
                raise InputError(f"ChunkPrediction.{name} must be {list(shape)} for F = {f} frames; got "
                                 f"{list(_shape(getattr(self, name)))}")
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        ps, cs = _shape(self.points), _shape(self.confidence)
        if len(ps) != 4 or ps[0] != f or ps[3] != 3:
            raise InputError(f"ChunkPrediction.points must be [F, H, W, 3] with F = {f}; got {list(ps)}")
        if cs != ps[:3]:
            raise InputError(f"ChunkPrediction.confidence must be [F, H, W] = {list(ps[:3])}; got {list(cs)}")
        if self.descriptors is not None:
            d = np.asarray(self.descriptors, dtype=np.float32)
            if d.ndim != 2 or d.shape[0] != f:
                raise InputError(f"ChunkPrediction.descriptors must be [F, D] with F = {f}; got {list(d.shape)}")
            object.__setattr__(self, "descriptors", d)

    def __len__(self) -> int:
        return len(self.frames)

    def index_of(self, frame: int) -> int:
        """The position of sequence frame `frame` in this chunk (ValueError: not in it)."""
        hits = np.flatnonzero(self.frames == frame)
        if not len(hits):
            raise ValueError(f"frame {frame} is not in this chunk ({self.frames[0]}..{self.frames[-1]})")
        return int(hits[0])


@dataclasses.dataclass(frozen=True, eq=False)
class LoopEdge:
    """A verified loop: chunk `j`'s frame mapped into chunk `i`'s (`sim3`: x_i = sim3(x_j)),
    from the query frames `frames` = (a frame of chunk i, a frame of chunk j), with the
    alignment's robust RMS residual and inlier count."""

    i: int
    j: int
    frames: tuple[int, int]
    sim3: Sim3
    residual: float
    inliers: int


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """The whole sequence's cameras in the first chunk's frame.

    extrinsics   [S, 3, 4] world-to-camera (OpenCV) of every frame, in the first chunk's
                 coordinates and scale
    intrinsics   [S, 3, 3]
    chunk_sim3   one `Sim3` per chunk, mapping the chunk's frame into the first chunk's
    frame_chunk  [S] int: the chunk whose prediction gave each frame's camera
    loops        the verified loop edges used by the pose graph (empty without loop closure)
    edge_residuals  [K-1] robust RMS residual of each consecutive alignment, in the
                 earlier chunk's units
    """

    extrinsics: np.ndarray
    intrinsics: np.ndarray
    chunk_sim3: tuple[Sim3, ...]
    frame_chunk: np.ndarray
    loops: tuple[LoopEdge, ...] = ()
    edge_residuals: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.extrinsics)

    @property
    def centers(self) -> np.ndarray:
        """[S, 3] camera centres -R^T t in the first chunk's frame."""
        from rvggt_jax.synthetic import camera_centers

        return camera_centers(self.extrinsics)
