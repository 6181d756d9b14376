"""What every dataset reader returns (`Scene`), frame sampling, and the errors.

A reader turns one scene folder, as distributed, into a `Scene`: the image files in
order, world-to-camera extrinsics `[S, 3, 4]` (OpenCV: x right, y down, z forward),
intrinsics `[S, 3, 3]` in the image files' pixels, and where to find the ground truth
(depth maps, a point cloud). Depth maps are read on demand (a 1000-frame scene does not
fit in memory as float arrays).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

# Defined in a leaf module (the PLY reader raises them too: no import cycle); every reader
# imports them from here.
from rvggt_jax.eval.datasets.errors import DatasetError, need_file

__all__ = ["DatasetError", "SAMPLING", "Scene", "need_file", "sample_indices"]


@dataclasses.dataclass
class Scene:
    """One scene's frames and ground truth.

    image_paths: S image files, in frame order. extrinsics [S, 3, 4] world-to-camera;
    intrinsics [S, 3, 3] in the image files' pixels; frame_ids: S names (file stems or
    numbers). depth_paths: S depth files or None; depth_reader(path) -> [H, W] float32
    metres (0 = no measurement); depth_intrinsics [S, 3, 3] in the depth maps' pixels
    (None = `intrinsics`). points_path: a ground-truth point cloud (PLY), or None.
    extrinsics is None for a folder of images without cameras."""

    dataset: str
    name: str
    image_paths: list[Path]
    extrinsics: np.ndarray | None
    intrinsics: np.ndarray | None
    frame_ids: list[str]
    depth_paths: list[Path] | None = None
    depth_reader: Callable[[Path], np.ndarray] | None = None
    depth_intrinsics: np.ndarray | None = None
    points_path: Path | None = None
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.image_paths)

    @property
    def has_depth(self) -> bool:
        return self.depth_paths is not None

    def depth(self, i: int) -> np.ndarray:
        """Ground-truth depth [H, W] float32 (metres, 0 = none) of frame i."""
        if self.depth_paths is None or self.depth_reader is None:
            raise DatasetError(f"{self.dataset} scene {self.name} has no depth maps")
        p = self.depth_paths[i]
        if not p.is_file():
            raise DatasetError(f"missing depth map: {p}")
        return self.depth_reader(p)

    def depth_camera(self, i: int) -> np.ndarray:
        """[3, 3] intrinsics of depth map i."""
        k = self.depth_intrinsics if self.depth_intrinsics is not None else self.intrinsics
        return k[i]

    def gt_points(self) -> np.ndarray:
        """The ground-truth point cloud [N, 3] (float64)."""
        if self.points_path is None:
            raise DatasetError(f"{self.dataset} scene {self.name} has no ground-truth point cloud")
        from rvggt_jax.eval.datasets.ply import read_ply_points

        return read_ply_points(need_file(self.points_path, "ground-truth point cloud"))

    def subset(self, indices: Sequence[int]) -> "Scene":
        """The scene restricted to the frames `indices` (in that order)."""
        idx = list(indices)

        def pick(a):
            return None if a is None else np.asarray(a)[idx]

        return dataclasses.replace(
            self, image_paths=[self.image_paths[i] for i in idx], extrinsics=pick(self.extrinsics),
            intrinsics=pick(self.intrinsics), frame_ids=[self.frame_ids[i] for i in idx],
            depth_paths=None if self.depth_paths is None else [self.depth_paths[i] for i in idx],
            depth_intrinsics=pick(self.depth_intrinsics), meta=dict(self.meta, indices=idx))


SAMPLING = ("first", "even", "random", "scannet")
"""How `sample_indices` picks N frames: the first N; N evenly spaced (first and last
included); N at random (sorted, seeded); or FastVGGT's ScanNet rule (the first frame,
then every step-th of the rest, step = max(1, (n - 1) // (N - 1)))."""


def sample_indices(n: int, *, stride: int = 1, frames: int | None = None, how: str = "first",
                   seed: int = 0) -> list[int]:
    """Frame indices of a protocol: every `stride`-th of n frames (keyframes), then at
    most `frames` of those picked by `how` (see `SAMPLING`); sorted."""
    if stride < 1:
        raise ValueError(f"stride must be at least 1; got {stride}")
    if frames is not None and frames < 1:
        raise ValueError(f"frames must be at least 1; got {frames}")
    if how not in SAMPLING:
        raise ValueError(f"unknown frame sampling {how!r}; use one of {', '.join(SAMPLING)}")
    idx = list(range(0, n, stride))
    if frames is None or len(idx) <= frames:
        return idx
    if how == "first":
        return idx[:frames]
    if how == "even":
        if frames == 1:
            return idx[:1]
        m = len(idx)
        return [idx[j] for j in sorted({round(k * (m - 1) / (frames - 1)) for k in range(frames)})]
    if how == "random":
        rng = np.random.default_rng(seed)
        return sorted(idx[j] for j in rng.choice(len(idx), size=frames, replace=False))
    # scannet
    if frames == 1:
        return idx[:1]
    rest = idx[1:]
    step = max(1, len(rest) // (frames - 1))
    return [idx[0]] + rest[::step][: frames - 1]
