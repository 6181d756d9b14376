"""Chunk predictions on disk, so that a long run holds one chunk in memory and a stopped
run resumes from the last finished chunk.

    store = ChunkStore(out / "chunks")
    store.save(k, prediction, depth=depth, valid=valid, meta={...})   # atomic
    store.done(k)                  # was chunk k finished?
    store.load(k)                  # ChunkPrediction over memory-mapped arrays

A chunk is a folder of `.npy` files (`chunk_00003/`), written under a temporary name and
renamed when complete: a run killed mid-write leaves no half chunk that looks finished.
Arrays are read back by frame (`FrameFile`), so aligning two chunks reads only the frames
they share and nothing stays resident after. When the points are a depth map unprojected with the chunk's cameras (the
usual VGGT output), only the depth is stored and `DepthPoints` unprojects the frames
asked for: 4 bytes a pixel instead of 12.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from rvggt_jax.sequence.prediction import ChunkPrediction

__all__ = ["ChunkStore", "DepthPoints", "FrameFile", "unproject_depth"]


def unproject_depth(depth: np.ndarray, extrinsics: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """World points [F, H, W, 3] float32 of depth maps [F, H, W] seen by cameras
    extrinsics [F, 3, 4] (world-to-camera) and intrinsics [F, 3, 3]: pixel (col, row) at
    integer coordinates is the ray K^-1 [col, row, 1] (`rvggt_jax.geometry`'s
    convention), scaled to its depth and taken to the world."""
    depth = np.asarray(depth, dtype=np.float64)
    f, h, w = depth.shape
    k_inv = np.linalg.inv(np.asarray(intrinsics, dtype=np.float64))
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([cols, rows, np.ones((h, w))], axis=-1)
    rays = np.einsum("fij,hwj->fhwi", k_inv, pix)
    cam = rays * depth[..., None]
    e = np.asarray(extrinsics, dtype=np.float64)
    r, t = e[:, :, :3], e[:, :, 3]
    # x_world = R^T (x_cam - t)
    world = np.einsum("fji,fhwj->fhwi", r, cam - t[:, None, None, :])
    return world.astype(np.float32)


class DepthPoints:
    """An array-like [F, H, W, 3] of the world points of depth maps [F, H, W] (any
    array-like, e.g. a memory map), unprojected when indexed by frame; pixels where
    `valid` [F, H, W] is False, or whose depth is not positive, are NaN."""

    def __init__(self, depth: Any, extrinsics: np.ndarray, intrinsics: np.ndarray, valid: Any = None):
        self.depth, self.valid = depth, valid
        self.extrinsics = np.asarray(extrinsics, dtype=np.float64)
        self.intrinsics = np.asarray(intrinsics, dtype=np.float64)
        self.shape = tuple(np.shape(depth)) + (3,)
        self.dtype = np.dtype(np.float32)
        self.ndim = 4

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, tuple):  # frames first, then the rest on the result
            return self[index[0]][(slice(None),) + index[1:]]
        frames = np.arange(self.shape[0])[index]
        single = np.ndim(frames) == 0
        frames = np.atleast_1d(frames)
        d = np.asarray(self.depth[frames], dtype=np.float32)
        pts = unproject_depth(d, self.extrinsics[frames], self.intrinsics[frames])
        bad = ~(np.isfinite(d) & (d > 0))
        if self.valid is not None:
            bad |= ~np.asarray(self.valid[frames], dtype=bool)
        pts[bad] = np.nan
        return pts[0] if single else pts

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


class ChunkStore:
    """Chunk predictions under `folder`, one sub-folder per finished chunk."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)

    def path(self, k: int) -> Path:
        return self.folder / f"chunk_{k:05d}"

    def done(self, k: int) -> bool:
        """Whether chunk k was saved completely."""
        return (self.path(k) / "meta.json").is_file()

    def save(self, k: int, pred: ChunkPrediction, *, depth: np.ndarray | None = None,
             valid: np.ndarray | None = None, meta: Mapping[str, Any] | None = None,
             **arrays: np.ndarray) -> Path:
        """Store chunk k: the prediction's arrays; with `depth` [F, H, W], the depth
        instead of the points (`load` unprojects it with the prediction's cameras);
        `valid` [F, H, W] bool (image content the outputs keep); `meta`, a JSON-able
        dict; further named arrays. Written to a temporary folder, then renamed."""
        final = self.path(k)
        tmp = self.folder / f".{final.name}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        content = dict(frames=pred.frames, extrinsics=pred.extrinsics, intrinsics=pred.intrinsics,
                       confidence=np.asarray(pred.confidence, dtype=np.float32), **arrays)
        if depth is not None:
            content["depth"] = np.asarray(depth, dtype=np.float32)
        else:
            content["points"] = np.asarray(pred.points, dtype=np.float32)
        if valid is not None:
            content["valid"] = np.asarray(valid, dtype=bool)
        if pred.descriptors is not None:
            content["descriptors"] = pred.descriptors
        for name, a in content.items():
            np.save(tmp / f"{name}.npy", np.asarray(a))
        # meta.json last: its presence marks the chunk complete (`done`)
        (tmp / "meta.json").write_text(json.dumps(dict(meta or {}), indent=1) + "\n")
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
        return final

    def array(self, k: int, name: str) -> "FrameFile | None":
        """Chunk k's array `name`, read by frame from its file (None when it has none)."""
        p = self.path(k) / f"{name}.npy"
        return FrameFile(p) if p.is_file() else None

    def meta(self, k: int) -> dict:
        return json.loads((self.path(k) / "meta.json").read_text())

    def load(self, k: int, points_from: str = "depth") -> ChunkPrediction:
        """Chunk k as a `ChunkPrediction` whose points and confidence are memory maps;
        points_from "depth": `DepthPoints` over the stored depth when there is one,
        "pointmap": the stored `world_points`. Pixels outside `valid` have NaN points
        and confidence 0 for alignment."""
        ext, intr = np.load(self.path(k) / "extrinsics.npy"), np.load(self.path(k) / "intrinsics.npy")
        valid = self.array(k, "valid")
        depth = self.array(k, "depth")
        if points_from == "pointmap" and self.array(k, "world_points") is not None:
            points = self.array(k, "world_points")
        elif depth is not None:
            points = DepthPoints(depth, ext, intr, valid)
        else:
            points = self.array(k, "points")
        conf = self.array(k, "confidence")
        if valid is not None:
            conf = _MaskedConfidence(conf, valid)
        desc = self.path(k) / "descriptors.npy"
        return ChunkPrediction(frames=np.load(self.path(k) / "frames.npy"), extrinsics=ext, intrinsics=intr,
                               points=points, confidence=conf, descriptors=np.load(desc) if desc.is_file() else None)


class FrameFile:
    """A stored .npy array [F, ...] read by frame: every read maps the file, copies the
    rows asked for and drops the mapping. A mapping kept open for the run would keep the
    pages the reads (and the kernel's readahead) touched resident, and a run holding
    every chunk would grow with S (+108 MiB at 10,000 frames, benchmarks/bench_long.py)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        head = np.load(self.path, mmap_mode="r")
        self.shape, self.dtype, self.ndim = tuple(head.shape), head.dtype, head.ndim
        del head

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> np.ndarray:
        return np.array(np.load(self.path, mmap_mode="r")[index])

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


class _MaskedConfidence:
    """confidence [F, H, W] with 0 where `valid` is False, read per frame on indexing."""

    def __init__(self, conf: Any, valid: Any):
        self.conf, self.valid = conf, valid
        self.shape, self.dtype, self.ndim = tuple(np.shape(conf)), np.dtype(np.float32), 3

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, tuple):
            return self[index[0]][(slice(None),) + index[1:]]
        c = np.asarray(self.conf[index], dtype=np.float32)
        return np.where(np.asarray(self.valid[index], dtype=bool), c, np.float32(0.0))

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)
