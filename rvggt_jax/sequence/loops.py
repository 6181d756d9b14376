"""Loop candidates: pairs of far-apart frames whose place descriptors look alike.

Cosine similarity between every two frames' descriptors [S, D], computed a block of rows
at a time so that memory stays O(block * S) (S = 10,000 frames: ~10 MB of similarities a block of 256
rows in float32, never the S x S matrix). Each frame keeps only its best partner among
the frames it may pair with (best later frame, and best earlier frame), so at most 2 S
pairs survive the blocks; those are then taken best first with non-maximum suppression
in (frame, frame) space, so one revisit, a band of similar pairs, gives one or a few
candidates.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rvggt_jax.errors import InputError

__all__ = ["LoopCandidate", "LoopOptions", "loop_candidates"]


@dataclasses.dataclass(frozen=True)
class LoopOptions:
    """How loops are proposed and verified.

    min_similarity  smallest cosine similarity of two frames' descriptors for a candidate
    min_gap         smallest distance in frames between a candidate's two frames
    max_loops       at most this many candidates (the most similar first)
    nms_radius      a candidate suppresses every weaker one within this many frames of it
                    in both of its frames (one revisit -> one or a few candidates)
    neighbourhood   frames on each side of a candidate frame (within its chunk) that go
                    with it to the verification: 2 sends up to 5 + 5 frames
    block           rows of the similarity matrix computed at a time
    """

    min_similarity: float = 0.8
    min_gap: int = 50
    max_loops: int = 16
    nms_radius: int = 25
    neighbourhood: int = 2
    block: int = 256

    def __post_init__(self) -> None:
        if not -1.0 <= self.min_similarity <= 1.0:
            raise InputError(f"LoopOptions.min_similarity is a cosine similarity in [-1, 1]; got "
                             f"{self.min_similarity}")
        for name in ("min_gap", "max_loops", "nms_radius", "neighbourhood"):
            if getattr(self, name) < 0:
                raise InputError(f"LoopOptions.{name} must be >= 0; got {getattr(self, name)}")
        if self.block < 1:
            raise InputError(f"LoopOptions.block must be >= 1; got {self.block}")


@dataclasses.dataclass(frozen=True)
class LoopCandidate:
    """Frames a < b of a proposed loop and their descriptors' cosine similarity."""

    a: int
    b: int
    similarity: float


def _normalised(descriptors) -> tuple[np.ndarray, np.ndarray]:
    """[S, D] -> unit rows [S, D] float32 and [S] bool: rows that have a direction."""
    d = np.asarray(descriptors, dtype=np.float32)
    if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
        raise InputError(f"loop descriptors must be [S, D] with S, D >= 1; got {list(d.shape)}")
    norms = np.linalg.norm(d, axis=1)
    ok = np.isfinite(norms) & (norms > 0)
    out = np.zeros_like(d)
    out[ok] = d[ok] / norms[ok, None]
    return out, ok


def _best_partners(unit: np.ndarray, ok: np.ndarray, allowed, options: LoopOptions) -> np.ndarray:
    """Each frame's most similar later and earlier allowed frame -> [P, 3] rows (a, b, sim),
    a < b, sim >= min_similarity. `allowed(rows, cols)` masks pairs [B, S] that may pair."""
    s = len(unit)
    col_best = np.full(s, -np.inf, dtype=np.float32)
    col_arg = np.full(s, -1)
    found = []
    cols = np.arange(s)
    for start in range(0, s, options.block):
        rows = np.arange(start, min(start + options.block, s))
        sim = unit[rows] @ unit.T
        # Only later frames (b > a), far enough apart, both with a descriptor.
        mask = (cols[None, :] - rows[:, None] >= max(options.min_gap, 1)) & ok[rows, None] & ok[None, :]
        if allowed is not None:
            mask &= allowed(rows, cols)
        sim = np.where(mask, sim, -np.inf)
        arg = sim.argmax(axis=1)
        best = sim[np.arange(len(rows)), arg]
        hit = best >= options.min_similarity
        found.append(np.stack([rows[hit], arg[hit], best[hit]], axis=1))
        # Keep each later frame's best earlier partner across the blocks.
        blk_arg = sim.argmax(axis=0)
        blk_best = sim[blk_arg, cols]
        better = blk_best > col_best
        col_best[better], col_arg[better] = blk_best[better], rows[blk_arg[better]]
    hit = col_best >= options.min_similarity
    found.append(np.stack([col_arg[hit], cols[hit], col_best[hit]], axis=1))
    pairs = np.concatenate(found, axis=0).astype(np.float64)
    return np.unique(pairs, axis=0) if len(pairs) else pairs.reshape(0, 3)


def loop_candidates(descriptors, options: LoopOptions = LoopOptions(), *, first_chunk=None,
                    last_chunk=None) -> list[LoopCandidate]:
    """Proposed loops among frames 0..S-1, the most similar first, at most `max_loops`.

    descriptors  [S, D] per-frame place descriptors (rows of zeros or NaN: no descriptor)
    first_chunk, last_chunk  [S] int, optional: the first and the last chunk holding each
                 frame; a pair (a, b) is then kept only when first_chunk[b] >=
                 last_chunk[a] + 2 (never the same or adjacent chunks, whose relative pose
                 the sequential alignment already gives)
    A pair needs cosine similarity >= min_similarity and b - a >= min_gap; non-maximum
    suppression drops a pair within `nms_radius` frames (in both a and b) of a better one.
    """
    unit, ok = _normalised(descriptors)
    s = len(unit)
    allowed = None
    if (first_chunk is None) != (last_chunk is None):
        raise InputError("loop_candidates needs both first_chunk and last_chunk, or neither")
    if first_chunk is not None:
        first, last = np.asarray(first_chunk), np.asarray(last_chunk)
        if first.shape != (s,) or last.shape != (s,):
            raise InputError(f"first_chunk and last_chunk must be [S] = [{s}]; got {list(first.shape)} and "
                             f"{list(last.shape)}")

        def allowed(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
            return first[None, cols] >= last[rows, None] + 2

    pairs = _best_partners(unit, ok, allowed, options)
    order = np.lexsort((pairs[:, 1], pairs[:, 0], -pairs[:, 2]))
    kept: list[LoopCandidate] = []
    r = options.nms_radius
    for a, b, sim in pairs[order]:
        if len(kept) >= options.max_loops:
            break
        if any(abs(a - k.a) <= r and abs(b - k.b) <= r for k in kept):
            continue
        kept.append(LoopCandidate(int(a), int(b), float(sim)))
    return kept
