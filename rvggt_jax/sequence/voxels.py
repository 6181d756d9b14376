"""A point cloud of bounded size built chunk by chunk: `VoxelCloud` averages the points
falling in each voxel and doubles the voxel size whenever more than `max_points` voxels
are occupied, so a run of any length writes at most `max_points` points while holding no
more than that plus one chunk's points."""

from __future__ import annotations

import numpy as np

__all__ = ["VoxelCloud"]

_HALF = 1 << 20  # voxel indices per axis are kept in [-2^20, 2^20)


class VoxelCloud:
    """Streaming voxel-grid downsampling.

    add(points [N, 3], colors [N, 3] uint8, confidence [N], frames [N]) accumulates;
    result() -> (points [M, 3] float32, colors [M, 3] uint8, confidence [M] float32,
    frames [M] int32), M <= max_points: per voxel the mean point, mean colour, mean
    confidence and the first frame that saw it. `voxel`: the starting size (None: set
    from the first points, 1/1000 of their extent).
    """

    def __init__(self, max_points: int = 2_000_000, voxel: float | None = None):
        if max_points < 1:
            raise ValueError(f"max_points must be at least 1; got {max_points}")
        self.max_points, self.voxel = int(max_points), voxel
        self._keys = np.zeros((0, 3), np.int64)
        self._sum = np.zeros((0, 7), np.float64)  # xyz, rgb, confidence
        self._count = np.zeros(0, np.int64)
        self._frame = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self._count)

    def add(self, points, colors, confidence, frames) -> None:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ok = np.isfinite(p).all(axis=1)
        if not ok.any():
            return
        vals = np.concatenate([p, np.asarray(colors, np.float64).reshape(-1, 3),
                               np.asarray(confidence, np.float64).reshape(-1, 1)], axis=1)[ok]
        fr = np.broadcast_to(np.asarray(frames, np.int64), (len(p),))[ok]
        if self.voxel is None:
            extent = float(np.max(np.ptp(vals[:, :3], axis=0))) if len(vals) > 1 else 0.0
            self.voxel = extent / 1000.0 if extent > 0 else 1e-3
        # far outliers share the border voxels rather than overflow the packed keys
        keys = np.clip(np.floor(vals[:, :3] / self.voxel), -_HALF, _HALF - 1).astype(np.int64)
        self._merge(keys, vals, np.ones(len(vals), np.int64), fr)
        while len(self) > self.max_points:
            self.voxel *= 2.0
            self._merge(np.floor_divide(self._keys, 2), self._sum, self._count, self._frame, replace=True)

    def _merge(self, keys, sums, counts, frames, replace: bool = False) -> None:
        if not replace:
            keys = np.concatenate([self._keys, keys])
            sums = np.concatenate([self._sum, sums])
            counts = np.concatenate([self._count, counts])
            frames = np.concatenate([self._frame, frames])
        # one int64 per voxel (21 bits an axis): a 1-D unique is ~10x faster than rows
        packed = ((keys[:, 0] + _HALF) << 42) | ((keys[:, 1] + _HALF) << 21) | (keys[:, 2] + _HALF)
        uniq, first_at, inv = np.unique(packed, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        self._keys = keys[first_at]
        self._sum = np.stack([np.bincount(inv, weights=sums[:, j], minlength=len(uniq))
                              for j in range(sums.shape[1])], axis=1)
        self._count = np.bincount(inv, weights=counts, minlength=len(uniq)).astype(np.int64)
        # the first frame of each voxel: sort by (voxel, frame), take each voxel's first
        order = np.lexsort((frames, inv))
        starts = np.flatnonzero(np.r_[True, np.diff(inv[order]) != 0])
        self._frame = frames[order][starts]

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        mean = self._sum / np.maximum(self._count, 1)[:, None]
        return (mean[:, :3].astype(np.float32), np.clip(np.round(mean[:, 3:6]), 0, 255).astype(np.uint8),
                mean[:, 6].astype(np.float32), self._frame.astype(np.int32))
