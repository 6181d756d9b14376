"""Compression configuration: presets, overrides, per-layer resolution, JSON."""

import dataclasses
import json

import pytest

from rvggt_jax.compression import PRESETS, CompressionConfig, make_compression, sigma_to_tile
from rvggt_jax.config import VGGTConfig

ALL = ("dense", "regime", "regime_paper", "regime_local", "fastvggt", "avggt", "merge_only", "kv_only",
       "no_cache", "no_size_bias", "no_anchor", "no_phase_shift")


def test_every_preset_exists_and_is_hashable():
    assert set(ALL) <= set(PRESETS)
    for name in ALL:
        cfg = VGGTConfig().with_compression(name)
        hash(cfg)
        assert cfg.compression.name == name
        assert cfg.compression.is_dense == (name == "dense")


@pytest.mark.parametrize("sigma,tile", [(1, (1, 1)), (1.0, (1, 1)), (1.3, (4, 3)), (1.5, (3, 2)), (1.7, (5, 3)),
                                        (2, (2, 1)), (3, (3, 1)), (4.0, (4, 1)), ((3, 2), (3, 2)), ((2, 2), (1, 1))])
def test_sigma_to_tile_as_the_authors(sigma, tile):
    assert sigma_to_tile(sigma) == tile


@pytest.mark.parametrize("bad", [0, 1.4, 2.5, -1, (2, 3), (0, 0), (3,)])
def test_bad_sigma_rejected(bad):
    with pytest.raises(ValueError):
        sigma_to_tile(bad)


def test_regime_layer_schedule_follows_hybrid_config():
    cc = make_compression("regime", 24)
    rho = [cc.layer_merge_ratio(i) for i in range(24)]
    assert rho == [0.99] * 10 + [0.5] * 8 + [0.99] * 6
    tiles = [cc.layer_tile(i) for i in range(24)]
    # The authors' code: sigma_shallow 1.5 below 10, merge-only 10-13, sigma_deep 1.7 from 14.
    assert tiles == [(3, 2)] * 10 + [(1, 1)] * 4 + [(5, 3)] * 10
    keys = [cc.cache_key(i) for i in range(24)]
    assert keys[:10] == ["band0_rho0.9900"] * 10
    assert keys[10:14] == [None] * 4
    assert keys[14:18] == ["band1_rho0.5000"] * 4
    assert keys[18:] == ["band2_rho0.9900"] * 6
    assert [cc.layer_metric(i) for i in (0, 10, 13, 14, 23)] == ["input", "norm1", "norm1", "input", "input"]
    assert cc.anchor and cc.phase_shift and cc.size_bias and not cc.kv_protect_saliency
    assert cc.match_scope == "sequence" and cc.protect == "saliency" and cc.alpha == 0.1


def test_regime_paper_and_spec_table_reading():
    cc = make_compression("regime_paper", 24)
    assert [cc.layer_tile(i) for i in range(24)] == [(3, 2)] * 10 + [(4, 3)] * 8 + [(5, 3)] * 6
    assert cc.kv_protect_saliency
    spec = make_compression("regime", 24, kv_bands=(10, 18))
    assert [spec.layer_tile(i) for i in range(24)] == [(3, 2)] * 10 + [(1, 1)] * 4 + [(4, 3)] * 4 + [(5, 3)] * 6


def test_overrides_by_band_and_by_layer():
    cfg = VGGTConfig().with_compression("regime", merge_ratio=(0.0, 0.0, 0.0), kv_sigma=(1.0, 1.0, 1.0))
    cc = cfg.compression
    assert all(cc.layer_merge_ratio(i) == 0 and cc.layer_tile(i) == (1, 1) for i in range(24))
    cc = make_compression("regime", 24, merge_ratio=(0.5, 0.25, 0.75), kv_sigma=(2, (3, 2), 1.7))
    assert [cc.layer_merge_ratio(i) for i in (0, 9, 10, 17, 18, 23)] == [0.5, 0.5, 0.25, 0.25, 0.75, 0.75]
    assert [cc.layer_tile(i) for i in (0, 9, 10, 14, 23)] == [(2, 1), (2, 1), (1, 1), (5, 3), (5, 3)]
    per_layer = tuple(i / 100 for i in range(24))
    cc = make_compression("merge_only", 24, merge_ratio=per_layer)
    assert [cc.layer_merge_ratio(i) for i in range(24)] == list(per_layer)
    cc = make_compression("kv_only", 24, kv_sigma=(3, 2))  # one tile everywhere but merge-only layers
    assert cc.layer_tile(0) == (3, 2) and cc.layer_tile(10) == (1, 1)


def test_invalid_overrides_rejected():
    with pytest.raises(ValueError):
        make_compression("regime", 24, merge_ratio=(0.5, 0.5))
    with pytest.raises(ValueError):
        make_compression("regime", 24, merge_ratio=(1.0, 0.5, 0.5))
    with pytest.raises(ValueError):
        make_compression("regime", 24, match_scope="scene")
    with pytest.raises(ValueError):
        make_compression("regime", 24, not_a_field=1)
    with pytest.raises(ValueError):
        make_compression("nope", 24)


def test_ablations_differ_from_regime_in_one_field():
    regime = make_compression("regime", 24)
    expect = {"merge_only": {"kv_sigma"}, "kv_only": {"merge_ratio"}, "no_cache": {"cache_band_starts"},
              "no_size_bias": {"size_bias"}, "no_anchor": {"anchor"}, "no_phase_shift": {"phase_shift"},
              "regime_local": {"match_scope"}}
    for name, fields in expect.items():
        cc = make_compression(name, 24)
        diff = {f.name for f in dataclasses.fields(cc) if getattr(cc, f.name) != getattr(regime, f.name)}
        assert diff == fields | {"name"}, name


def test_fastvggt_and_avggt_presets():
    fv = make_compression("fastvggt", 24)
    assert all(fv.layer_merge_ratio(i) == 0.9 and fv.layer_tile(i) == (1, 1) for i in range(24))
    assert fv.protect == "stride" and not fv.size_bias and fv.cache_band_starts == ()
    av = make_compression("avggt", 24)
    assert [av.layer_kind(i) for i in range(24)] == ["frame"] * 9 + ["compressed"] * 15
    assert all(av.layer_tile(i) == (2, 1) for i in range(9, 24))
    assert not av.anchor and not av.phase_shift and av.layer_merge_ratio(12) == 0


def test_json_round_trip_through_vggt_config():
    cfg = VGGTConfig().with_compression("regime_paper", alpha=0.2)
    d = json.loads(json.dumps(cfg.to_dict()))
    back = VGGTConfig.from_dict(d)
    assert back == cfg and hash(back) == hash(cfg)
    assert CompressionConfig.from_dict(d["compression"]) == cfg.compression


def test_other_depth_rescales_layer_indices():
    cc = make_compression("regime", 12)
    assert cc.merge_bands == (5, 9) and cc.kv_bands == (5, 7)
    assert cc.merge_only_layers == (5, 6) and cc.no_cache_layers == (5, 6)
    assert [cc.layer_merge_ratio(i) for i in range(12)] == [0.99] * 5 + [0.5] * 4 + [0.99] * 3
