"""Which frames each chunk holds: `plan_chunks(S, C, O)`.

Every chunk has exactly `C` frames (the last one is moved back to end at the sequence's
end, overlapping its neighbour by more than `O`), so a jitted model compiles once for
the whole sequence: one input shape.
"""

from __future__ import annotations

import numpy as np

from rvggt_jax.errors import InputError

__all__ = ["check_chunking", "plan_chunks"]


def check_chunking(chunk_frames: int, overlap: int) -> None:
    """`InputError` naming the value when `chunk_frames` / `overlap` cannot chain chunks:
    a chunk needs 2 frames, consecutive chunks need a shared frame to be aligned on, and
    the overlap must leave each chunk at least one new frame."""
    if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, (int, np.integer)) or chunk_frames < 2:
        raise InputError(f"chunk_frames must be an integer of at least 2; got {chunk_frames!r} (e.g. 60)")
    if isinstance(overlap, bool) or not isinstance(overlap, (int, np.integer)) or overlap < 1:
        raise InputError(f"overlap must be at least 1: consecutive chunks are aligned on the frames they share; "
                         f"got {overlap!r} (e.g. {max(1, chunk_frames // 4)})")
    if overlap >= chunk_frames:
        raise InputError(f"overlap must be smaller than chunk_frames ({chunk_frames}); got {overlap} "
                         f"(e.g. {max(1, chunk_frames // 4)})")


def plan_chunks(num_frames: int, chunk_frames: int, overlap: int) -> list[np.ndarray]:
    """The frame indices [C] of each chunk of a sequence of `num_frames` frames: chunk k
    starts at k * (C - O); the last chunk is [S - C, S). A sequence of at most C frames is
    one chunk of all of them. Consecutive chunks share at least `overlap` frames."""
    check_chunking(chunk_frames, overlap)
    if num_frames < 1:
        raise InputError(f"a sequence needs at least 1 frame; got {num_frames}")
    if num_frames <= chunk_frames:
        return [np.arange(num_frames)]
    step = chunk_frames - overlap
    starts = list(range(0, num_frames - chunk_frames, step)) + [num_frames - chunk_frames]
    return [np.arange(s, s + chunk_frames) for s in starts]
