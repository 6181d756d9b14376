"""benchmarks/bench_ab.py's arithmetic and argument checks (the comparison itself runs two
compiled forwards: a benchmark, not a test)."""

import numpy as np
import pytest

from benchmarks import bench_ab


def test_pair_summary_reads_the_pairs_not_the_sides():
    # B is 2% faster than A in every pair but one, which a slow stretch split; the host's
    # speed moves both sides 1.5x between pairs, more often during B's forwards: the
    # pairs' median says 0.98, the sides' medians say 1.47
    a = [1.0, 1.0, 1.5, 1.5, 1.0]
    b = [0.98, 1.47, 1.47, 1.47, 0.98]
    s = bench_ab.pair_summary(a, b)
    assert s["ratio"] == pytest.approx(0.98)
    assert s["ratio_median"] == pytest.approx(1.47)
    assert s["ratio_min"] == pytest.approx(0.98)
    assert s["q1"] == pytest.approx(0.98) and s["q3"] == pytest.approx(0.98)
    with pytest.raises(ValueError, match="as many times"):
        bench_ab.pair_summary([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="at least one"):
        bench_ab.pair_summary([], [])


def test_max_rel_diff_over_outputs():
    a = {"depth": np.array([1.0, -4.0]), "pose_enc": np.array([2.0])}
    b = {"depth": np.array([1.0, -4.0]), "pose_enc": np.array([2.5])}
    assert bench_ab.max_rel_diff(a, b) == pytest.approx(0.25)
    assert bench_ab.max_rel_diff(a, a) == 0.0


def test_a_tree_is_a_folder_or_a_revision(tmp_path):
    (tmp_path / "rvggt_jax").mkdir()
    made = []
    assert bench_ab._tree(str(tmp_path), made) == tmp_path and made == []
    with pytest.raises(SystemExit, match="neither a source tree"):
        bench_ab._tree(str(tmp_path / "nothing-here"), made)
    assert made == []
