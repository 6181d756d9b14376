"""Static index builders (numpy, computed at trace time from shapes and configuration).

Token order of the global blocks: the sequence of one batch element holds N = S*L
tokens, L = num_special + h*w per frame: `num_special` tokens (camera, registers), then the h*w
patches row-major. Position n -> frame n // L, local index n % L; patch (i, j) of a frame
sits at local index num_special + i*w + j.

Everything here is a pure function of the static `Geometry` (and configuration), cached,
and returns read-only numpy arrays, so the compressed block never branches on data and
every shape is static.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import numpy as np


@dataclass(frozen=True)
class Geometry:
    """The static shape of a global block's sequence: `frames` frames, each `num_special`
    special tokens then an h x w grid of patches (row-major)."""

    frames: int
    h: int
    w: int
    num_special: int

    @property
    def per_frame(self) -> int:
        """L: tokens per frame."""
        return self.num_special + self.h * self.w

    @property
    def tokens(self) -> int:
        """N = S * L: tokens of the sequence."""
        return self.frames * self.per_frame

    @property
    def patches(self) -> int:
        """T = h * w: patches per frame."""
        return self.h * self.w


jax.tree_util.register_static(Geometry)


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


class TokenLayout(NamedTuple):
    """Per-position facts of the sequence, each [N]."""

    frame: np.ndarray  # frame index f
    local: np.ndarray  # index inside the frame
    special: np.ndarray  # bool: camera / register token
    row: np.ndarray  # patch row i (-1 for specials)
    col: np.ndarray  # patch column j (-1 for specials)


@functools.lru_cache(maxsize=64)
def token_layout(geom: Geometry) -> TokenLayout:
    L = geom.per_frame
    n = np.arange(geom.tokens)
    frame, local = n // L, n % L
    special = local < geom.num_special
    patch = np.where(special, -1, local - geom.num_special)
    row = np.where(special, -1, patch // geom.w)
    col = np.where(special, -1, patch % geom.w)
    return TokenLayout(*(_ro(a) for a in (frame, local, special, row, col)))


# ---------------------------------------------------------------------------------------
# dst cells
# ---------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=256)
def dst_cells(h: int, w: int, frame: int, seed: int, cell: tuple[int, int] = (2, 2)) -> np.ndarray:
    """Local patch indices (i*w + j) of the dst patches of one frame: one per cell of
    `cell` = (rows, cols) patches, cells aligned to the grid from (0, 0), partial cells at
    odd edges included, in row-major cell order.

    seed >= 0: the patch inside each cell is drawn uniformly (among the cell's real
    patches) from a generator seeded by (seed, frame); seed < 0: the top-left patch."""
    ch, cw = cell
    rng = np.random.default_rng([seed, frame]) if seed >= 0 else None
    out = []
    for ci in range(0, h, ch):
        rows = min(ch, h - ci)
        for cj in range(0, w, cw):
            cols = min(cw, w - cj)
            pick = int(rng.integers(rows * cols)) if rng is not None else 0
            out.append((ci + pick // cols) * w + cj + pick % cols)
    return _ro(np.asarray(out, np.int64))


def num_cells(h: int, w: int, cell: tuple[int, int] = (2, 2)) -> int:
    return -(-h // cell[0]) * -(-w // cell[1])


class Partition(NamedTuple):
    """dst / src split of the sequence (the authors' bipartite partition).

    dst = every token of frame 0, the special tokens of every frame and one patch per
    2x2 cell of every other frame; src = all other patches (frames >= 1 only)."""

    is_dst: np.ndarray  # [N] bool
    dst_pos: np.ndarray  # [N_dst] positions, ascending
    src_pos: np.ndarray  # [N_src] positions, ascending (frame-major: frames 1..S-1)
    dst_rank: np.ndarray  # [N] index of a position in dst_pos (-1 for src)
    src_rank: np.ndarray  # [N] index of a position in src_pos (-1 for dst)
    src_pos_f: np.ndarray  # [S-1, n_src_f] the src of frames 1..S-1
    dst_rank_f: np.ndarray  # [S-1, n_dst_f] dst_rank of the dst of frames 1..S-1
    dst_first_src: np.ndarray  # [N_dst + N_src] positions of the (dst ; src) concatenation
    perm_to_pos: np.ndarray  # [N] index into (dst ; src) of every position


@functools.lru_cache(maxsize=64)
def partition(geom: Geometry, seed: int) -> Partition:
    frames, h, w, num_special = geom.frames, geom.h, geom.w, geom.num_special
    L = geom.per_frame
    N = geom.tokens
    is_dst = np.zeros(N, bool)
    is_dst[:L] = True
    for f in range(1, frames):
        base = f * L
        is_dst[base: base + num_special] = True
        is_dst[base + num_special + dst_cells(h, w, f, seed)] = True
    dst_pos = np.flatnonzero(is_dst)
    src_pos = np.flatnonzero(~is_dst)
    dst_rank = np.full(N, -1, np.int64)
    dst_rank[dst_pos] = np.arange(dst_pos.size)
    src_rank = np.full(N, -1, np.int64)
    src_rank[src_pos] = np.arange(src_pos.size)
    if frames > 1:
        src_pos_f = src_pos.reshape(frames - 1, -1)
        dst_pos_f = dst_pos[L:].reshape(frames - 1, -1)
    else:
        src_pos_f = np.zeros((0, h * w - num_cells(h, w)), np.int64)
        dst_pos_f = np.zeros((0, num_special + num_cells(h, w)), np.int64)
    dst_first_src = np.concatenate([dst_pos, src_pos])
    perm_to_pos = np.empty(N, np.int64)
    perm_to_pos[dst_first_src] = np.arange(N)
    return Partition(*(_ro(a) for a in (
        is_dst, dst_pos, src_pos, dst_rank, src_rank, src_pos_f, dst_rank[dst_pos_f],
        dst_first_src, perm_to_pos)))


# ---------------------------------------------------------------------------------------
# K/V sub-grid
# ---------------------------------------------------------------------------------------


def phase_offsets(frame: np.ndarray | int, tile: int, phase_shift: bool) -> tuple[np.ndarray, np.ndarray]:
    """(r_f, c_f) = ((f div t) mod t, f mod t), or (0, 0) without phase shift."""
    f = np.asarray(frame)
    if not phase_shift:
        return np.zeros_like(f), np.zeros_like(f)
    return (f // tile) % tile, f % tile


def grid_keep(row: np.ndarray, col: np.ndarray, frame: np.ndarray, h: int, w: int,
              tile: tuple[int, int], phase_shift: bool) -> np.ndarray:
    """Phase-shifted sub-grid rule for patches (row, col) of `frame` (arrays)."""
    t, k = tile
    if (t, k) == (1, 1):
        return np.ones(np.shape(row), bool)
    rf, cf = phase_offsets(frame, t, phase_shift)
    inside = (row >= 0) & (row < (h // t) * t) & (col >= 0) & (col < (w // t) * t)
    return inside & (((row - rf) % t) < k) & (((col - cf) % t) < k)


@functools.lru_cache(maxsize=256)
def kv_static_keep(geom: Geometry, tile: tuple[int, int], phase_shift: bool, anchor: bool) -> np.ndarray:
    """[N] bool: the positions kept as K/V for static reasons (camera/register tokens,
    frame 0 when `anchor`, patches on the (phase-shifted) sub-grid of `tile`). A layer's
    mask is `LayerPlan.kv_keep`."""
    lay = token_layout(geom)
    keep = lay.special | grid_keep(lay.row, lay.col, lay.frame, geom.h, geom.w, tile, phase_shift)
    if anchor:
        keep = keep | (lay.frame == 0)
    return _ro(keep)


# ---------------------------------------------------------------------------------------
# Protection
# ---------------------------------------------------------------------------------------


def saliency_protect_count(geom: Geometry, alpha: float) -> int:
    """Protected patches per frame >= 1: max(1, floor(alpha*T)) (0 when alpha is 0)."""
    return 0 if alpha <= 0 else max(1, int(alpha * geom.patches))


@functools.lru_cache(maxsize=64)
def stride_protected(n_tokens: int, alpha: float) -> np.ndarray:
    """FastVGGT's uniform protection: floor(alpha*N) positions at stride N // that count."""
    count = int(n_tokens * alpha)
    if count <= 0:
        return _ro(np.zeros(0, np.int64))
    step = max(1, n_tokens // count)
    return _ro(np.arange(0, n_tokens, step)[:count])
