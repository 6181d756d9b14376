"""Exact values of the static index builders: layout, dst cells (odd grids), partition,
phase offsets, kept K/V masks, kept fractions and cross-frame coverage, protection."""

import numpy as np
import pytest

from rvggt_jax.compression.partition import (
    Geometry,
    dst_cells,
    grid_keep,
    kv_static_keep,
    num_cells,
    partition,
    phase_offsets,
    saliency_protect_count,
    stride_protected,
    token_layout,
)


def test_token_layout_exact():
    lay = token_layout(Geometry(2, 2, 3, 5))
    assert lay.frame.tolist() == [0] * 11 + [1] * 11
    assert lay.special.tolist() == ([True] * 5 + [False] * 6) * 2
    assert lay.row.tolist() == ([-1] * 5 + [0, 0, 0, 1, 1, 1]) * 2
    assert lay.col.tolist() == ([-1] * 5 + [0, 1, 2, 0, 1, 2]) * 2


def test_dst_cells_top_left_on_odd_grid():
    # 3 x 5: cells rows {0-1, 2}, cols {0-1, 2-3, 4}; top-left of each, row-major.
    assert dst_cells(3, 5, 1, -1).tolist() == [0, 2, 4, 10, 12, 14]
    assert num_cells(3, 5) == 6 and num_cells(4, 4) == 4 and num_cells(1, 1) == 1


@pytest.mark.parametrize("h,w", [(3, 5), (5, 7), (4, 6), (1, 3), (7, 1), (12, 16)])
def test_dst_cells_one_per_aligned_cell(h, w):
    for frame in range(1, 6):
        cells = dst_cells(h, w, frame, 33)
        i, j = cells // w, cells % w
        assert cells.size == num_cells(h, w)
        # cell index (i div 2, j div 2) of every dst is its row-major cell number: the grid
        # alignment holds on odd widths (no per-row drift).
        ncol = -(-w // 2)
        assert ((i // 2) * ncol + j // 2).tolist() == list(range(cells.size))
        assert (i < h).all() and (j < w).all()
    # partial corner cell of an odd grid has one patch: it is always the dst
    assert dst_cells(3, 5, 2, 33)[-1] == 14
    # a fixed choice: deterministic, but not the same cell offset everywhere
    a = dst_cells(12, 16, 1, 33)
    assert (a == dst_cells(12, 16, 1, 33)).all()
    assert len({(int(x) // 16 % 2, int(x) % 16 % 2) for x in a}) > 1


def test_partition_exact_small():
    part = partition(Geometry(2, 2, 3, 5), -1)
    assert part.dst_pos.tolist() == list(range(16)) + [16, 18]
    assert part.src_pos.tolist() == [17, 19, 20, 21]
    assert part.src_pos_f.tolist() == [[17, 19, 20, 21]]
    assert part.dst_rank_f.tolist() == [[11, 12, 13, 14, 15, 16, 17]]
    assert part.dst_rank[[0, 16, 18, 17]].tolist() == [0, 16, 17, -1]
    assert part.src_rank[[17, 21, 0]].tolist() == [0, 3, -1]
    assert (part.dst_first_src[part.perm_to_pos] == np.arange(22)).all()


@pytest.mark.parametrize("s,h,w", [(1, 3, 3), (3, 5, 7), (4, 12, 16)])
def test_partition_counts(s, h, w):
    part = partition(Geometry(s, h, w, 5), 33)
    L = 5 + h * w
    assert part.is_dst[:L].all()
    assert part.dst_pos.size == L + (s - 1) * (5 + num_cells(h, w))
    assert part.src_pos.size == (s - 1) * (h * w - num_cells(h, w))
    assert part.is_dst.sum() + (~part.is_dst).sum() == s * L
    lay = token_layout(Geometry(s, h, w, 5))
    assert (~lay.special[part.src_pos]).all() and (lay.frame[part.src_pos] >= 1).all()


def test_phase_offsets_exact():
    r, c = phase_offsets(np.arange(10), 3, True)
    assert r.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 0]
    assert c.tolist() == [0, 1, 2, 0, 1, 2, 0, 1, 2, 0]
    r, c = phase_offsets(np.arange(6), 5, True)
    assert r.tolist() == [0, 0, 0, 0, 0, 1] and c.tolist() == [0, 1, 2, 3, 4, 0]
    r, c = phase_offsets(np.arange(4), 3, False)
    assert r.tolist() == [0] * 4 and c.tolist() == [0] * 4


def test_kv_keep_mask_exact():
    # S=2, 3 x 4 grid, tile (3, 2): truncated grid 3 x 3; frame 1 offsets (0, 1):
    # rows 0, 1 and columns 1, 2 -> local patches 1, 2, 5, 6.
    keep = kv_static_keep(Geometry(2, 3, 4, 5), (3, 2), True, True)
    assert keep[:17].all()  # frame 0 (anchor)
    assert keep[17:22].all()  # frame 1 specials
    assert np.flatnonzero(keep[22:]).tolist() == [1, 2, 5, 6]
    no_anchor = kv_static_keep(Geometry(2, 3, 4, 5), (3, 2), True, False)
    assert np.flatnonzero(no_anchor[5:17]).tolist() == [0, 1, 4, 5] and no_anchor[:5].all()
    no_phase = kv_static_keep(Geometry(2, 3, 4, 5), (3, 2), False, True)
    assert np.flatnonzero(no_phase[22:]).tolist() == [0, 1, 4, 5]
    assert kv_static_keep(Geometry(2, 3, 4, 5), (1, 1), True, False).all()


@pytest.mark.parametrize("tile,h,w", [((3, 2), 12, 15), ((5, 3), 10, 15), ((4, 3), 12, 16), ((2, 1), 8, 6),
                                      ((3, 1), 9, 9)])
def test_kept_fraction_is_k_over_t_squared(tile, h, w):
    t, k = tile
    s = 7
    keep = kv_static_keep(Geometry(s, h, w, 5), tile, True, False)
    L = 5 + h * w
    for f in range(s):
        patches = keep[f * L + 5:(f + 1) * L]
        assert patches.sum() * t * t == h * w * k * k


@pytest.mark.parametrize("tile,h,w", [((3, 2), 12, 16), ((5, 3), 12, 16), ((4, 3), 12, 16), ((2, 1), 7, 9)])
def test_union_over_t_squared_frames_covers_truncated_grid(tile, h, w):
    t, _ = tile
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    inside = (ii < (h // t) * t) & (jj < (w // t) * t)
    for f0 in (0, 1, 5):
        union = np.zeros((h, w), bool)
        for f in range(f0, f0 + t * t):
            union |= grid_keep(ii, jj, np.full_like(ii, f), h, w, tile, True)
        assert (union == inside).all()
        # without the phase shift every frame keeps the same sub-grid
        same = grid_keep(ii, jj, np.full_like(ii, f0), h, w, tile, False)
        assert same.sum() < inside.sum()


def test_protection_counts():
    assert saliency_protect_count(Geometry(2, 12, 16, 5), 0.1) == 19
    assert saliency_protect_count(Geometry(2, 2, 3, 5), 0.1) == 1  # max(1, floor(0.6))
    assert saliency_protect_count(Geometry(2, 12, 16, 5), 0.0) == 0
    assert stride_protected(100, 0.1).tolist() == list(range(0, 100, 10))
    assert stride_protected(105, 0.1).tolist() == list(range(0, 100, 10))  # N // 10 = 10, first 10
    assert stride_protected(5, 0.1).size == 0


@pytest.mark.parametrize("b, p, n, frac", [(2, 50, 10, 0.3), (1, 1000, 200, 0.05), (3, 7, 7, 0.5), (2, 20, 30, 0.5),
                                           (1, 64, 5, 0.0), (1, 64, 5, 1.0)])
def test_compaction_is_a_stable_argsort_of_the_flags(b, p, n, frac):
    """`merge.compact` (running counts and a scatter, no sort) gives the first n entries of a
    stable argsort of ~valid: the True entries in order, then the False ones."""
    import jax
    import jax.numpy as jnp

    from rvggt_jax.compression.merge import compact

    valid = np.random.default_rng(p + n).random((b, p)) < frac
    order, ok = jax.jit(compact, static_argnums=1)(jnp.asarray(valid), n)
    want = np.argsort(~valid, axis=-1, kind="stable")[:, :n]
    np.testing.assert_array_equal(np.asarray(order), want)
    np.testing.assert_array_equal(np.asarray(ok), np.take_along_axis(valid, want, axis=-1))
