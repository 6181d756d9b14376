"""The cost model's bookkeeping (its agreement with the traced shapes is in
tests/compression/test_block.py::test_cost_model_agrees_with_traced_shapes)."""

import pytest

import rvggt_jax
from rvggt_jax.compression import PRESETS
from rvggt_jax.config import VGGTConfig

BASE = VGGTConfig(embed_dim=256, num_heads=4)


def test_dense_predicts_one():
    rep = rvggt_jax.cost_report(BASE.with_compression("dense"), 16, 168, 224)
    assert rep["predicted_speedup"] == pytest.approx(1.0)
    assert rep["global_attention_ratio"] == pytest.approx(1.0)
    assert all(r["queries"] == r["kv_slots"] == 16 * 197 for r in rep["layers"])


def test_regime_counts_at_64_frames():
    rep = rvggt_jax.cost_report(BASE.with_compression("regime"), 64, 168, 224)
    n = 64 * 197
    rows = rep["layers"]
    assert rep["tokens"] == n and rep["grid"] == (12, 16)
    # rho 0.99 is capped by the protected patches: N_m = 5 + 48 dst + 19 protected per frame >= 1, + frame 0
    assert rows[0]["queries"] == 197 + 63 * (5 + 48 + 19) == 4733
    assert rows[10]["queries"] == n - int(0.5 * n) == rows[10]["kv_slots"]
    assert [r["match"] for r in rows].count("compute") == 7  # 0, 10, 11, 12, 13, 14, 18
    assert sum(1 for r in rows if r["match_flops"] > 0) == 7
    # every dynamic K/V slot attended (a capacity past the bound): 3.09; with the default
    # capacity (1.5 times the expected fill) the layers attend with fewer slots
    full = rvggt_jax.cost_report(BASE.with_compression("regime", kv_capacity=1e3), 64, 168, 224)
    assert full["predicted_speedup"] == pytest.approx(3.09, abs=0.01)
    assert rep["predicted_speedup"] == pytest.approx(3.25, abs=0.01)
    for r, f in zip(rows, full["layers"]):
        assert r["kv_dynamic_bound"] == f["kv_dynamic"] == f["kv_dynamic_bound"] >= r["kv_dynamic"]
        assert r["kv_dynamic"] >= 1.5 * (r["kv_filled_expected"] - r["kv_fixed"]) or r["kv_dynamic"] == f["kv_dynamic"]
    assert rep["global_attention_ratio"] < 0.13
    for r in rows:
        assert r["kv_fixed"] + r["kv_dynamic"] + r["kv_duplicates"] == r["kv_slots"]
        assert r["kv_fixed"] <= r["kv_filled_expected"] <= r["kv_slots"]


@pytest.mark.parametrize("name", PRESETS)
def test_totals_add_up(name):
    rep = rvggt_jax.cost_report(BASE.with_compression(name), 8, 168, 224)
    assert rep["global_flops"] == sum(r["flops"] for r in rep["layers"])
    assert rep["aggregator_flops"] == rep["global_flops"] + rep["frame_block_flops"]
    assert rep["predicted_speedup"] == pytest.approx(rep["dense_aggregator_flops"] / rep["aggregator_flops"])
    assert 1.0 <= rep["predicted_speedup_with_patch_embed"] <= rep["predicted_speedup"] + 1e-9


def test_speedup_grows_with_frames():
    sp = [rvggt_jax.cost_report(BASE.with_compression("regime"), s, 168, 224)["predicted_speedup"]
          for s in (8, 16, 32, 64)]
    assert sp == sorted(sp) and sp[0] > 1.3


def test_bad_image_size_rejected():
    with pytest.raises(ValueError):
        rvggt_jax.cost_report(BASE.with_compression("regime"), 8, 170, 224)
