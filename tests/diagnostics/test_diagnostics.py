"""rvggt_jax.diagnostics on constructed cases with known answers: attention of a known
rank gives that r95, the rank streams (no [N, N] anywhere), a profile with known bands
gives them back (and the paper's profile the paper's schedule), the phase-shifted grid's
union coverage matches its closed form, Psi maps and protected patches are the
forward's, and preset files round-trip or fail naming the problem."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax import diagnostics as D
from rvggt_jax.compression.config import PRESETS, make_compression
from rvggt_jax.compression.partition import Geometry


# ---------------------------------------------------------------------------------------
# rank
# ---------------------------------------------------------------------------------------


def block_qk(rank: int, n: int, idx: np.ndarray, heads: int = 2, d: int = 8, scale: float = 40.0):
    """q [1, n, H, d], k [1, n, H, d] whose softmax attention rows at the sampled queries
    `idx` have rank `rank` with equal energies: key j belongs to cluster j % rank, the
    j-th sampled query to cluster j % rank (equally many per cluster), and a query attends
    (to float32 precision) uniformly to its cluster's keys."""
    basis = np.eye(d, dtype=np.float32)[: rank] * scale
    k = basis[np.arange(n) % rank]
    q = np.zeros((n, d), np.float32)
    q[idx] = basis[np.arange(len(idx)) % rank]
    stack = lambda a: jnp.asarray(np.repeat(a[None, :, None, :], heads, axis=2))
    return stack(q), stack(k)


@pytest.mark.parametrize("rank", [1, 3, 8])
def test_attention_of_known_rank_gives_that_r95(rank):
    n, m = 96, 24
    idx = D.sample_queries(n, m, seed=1)
    q, k = block_qk(rank, n, idx)
    rows = D.attention_rows(q, k, idx)
    assert rows.shape == (1, 2, m, n)
    np.testing.assert_allclose(np.asarray(rows).sum(-1), 1.0, rtol=1e-5)
    # equal energies in `rank` directions: r95 = ceil(0.95 * rank) = rank for rank < 20
    assert D.r95(rows[0, 0]) == rank
    r, s = jax.jit(D.head_ranks)(q, k, idx)
    assert r.shape == (1, 2) and s.shape == (1, 2, m)
    assert np.all(np.asarray(r) == rank)


def test_r95_counts_squared_singular_values():
    """Energies 0.5, 0.3, 0.14, 0.04, 0.02: 95% is reached at 4 (with the singular values
    themselves instead of their squares it would be 5)."""
    energy = np.array([0.5, 0.3, 0.14, 0.04, 0.02])
    rows = np.zeros((5, 40))
    rows[np.arange(5), np.arange(5) * 7] = np.sqrt(energy)
    assert D.r95(rows) == 4
    assert int(D.r95_of_spectrum(jnp.asarray(np.sqrt(energy), jnp.float32))) == 4
    rng = np.random.default_rng(0)
    rand = jax.nn.softmax(jnp.asarray(rng.normal(size=(16, 50)) * 3), axis=-1)
    assert D.r95(rand) == int(D.r95_of_spectrum(D.singular_values(rand)))
    assert D.r95(np.zeros((4, 9))) == 0
    with pytest.raises(ValueError, match=r"\[m, N\]"):
        D.r95(np.ones((2, 3, 4)))


def test_rank_streams_over_the_sequence():
    """No value of the traced computation is [N, N] (m query rows against N keys only)."""
    n, m = 144, 16
    idx = D.sample_queries(n, m)
    q, k = block_qk(4, n, idx)
    jaxpr = jax.make_jaxpr(lambda q, k: D.head_ranks(q, k, idx))(q, k)

    def shapes(jx):
        for eqn in jx.eqns:
            for v in eqn.outvars:
                yield tuple(getattr(v.aval, "shape", ()))
            for p in eqn.params.values():
                inner = getattr(p, "jaxpr", None)
                if inner is not None:
                    yield from shapes(getattr(inner, "jaxpr", inner))

    seen = list(shapes(jaxpr.jaxpr))
    assert any(s.count(n) == 1 and m in s for s in seen)  # the [.., m, N] rows are there
    assert not [s for s in seen if s.count(n) >= 2]


def test_sample_queries_is_static_and_bounded():
    a, b = D.sample_queries(50, 20, seed=3), D.sample_queries(50, 20, seed=3)
    assert np.array_equal(a, b) and len(set(a.tolist())) == 20 and np.all(np.diff(a) > 0)
    assert len(D.sample_queries(10, 256)) == 10
    with pytest.raises(ValueError, match="m must be >= 1"):
        D.sample_queries(10, 0)


# ---------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------


def u_profile(mid: int, deep: int, depth: int = 24, low=(0.04, 0.01), high=0.35, seed=0):
    """A profile with known bands: low flanks with noise, a bumped middle band."""
    rng = np.random.default_rng(seed)
    p = np.empty(depth)
    p[:mid] = low[0] + rng.uniform(0, 0.02, mid)
    p[mid:deep] = high + 0.05 * np.sin(np.linspace(0, np.pi, deep - mid))
    p[deep:] = low[1] + rng.uniform(0, 0.02, depth - deep)
    return p


@pytest.mark.parametrize("bands", [(10, 18), (4, 9), (0, 7), (15, 24)])
def test_a_profile_with_known_bands_gives_them_back(bands):
    assert D.find_bands(u_profile(*bands)) == bands
    comp, info = D.propose(u_profile(*bands))
    assert comp.merge_bands == bands and comp.kv_bands == bands
    assert info["bands"]["middle"] == list(bands)


def test_the_papers_profile_gives_the_papers_schedule():
    """Shallow rank 20 of 256, a middle band at 90 of 256, a near-rank-1 deep band (the
    paper's Figure 1): the rule gives back rho 0.99 / 0.50 / 0.99 and sigma 1.5 / 1.3 /
    1.7, in a U."""
    p = np.r_[np.full(10, 20 / 256), np.full(8, 90 / 256), np.full(6, 1 / 256)]
    comp, info = D.propose(p)
    assert comp.merge_bands == (10, 18)
    assert comp.merge_ratio == (0.99, 0.5, 0.99)
    assert comp.kv_sigma == ((3, 2), (4, 3), (5, 3))  # sigma 1.5, 1.3, 1.7 as tiles
    assert comp.cache_band_starts == (0, 10, 18) and comp.no_cache_layers == (10, 11, 12, 13)
    assert comp.name == "calibrated" and not comp.is_dense
    # monotone rules: more rank, less merging and denser K/V
    ranks = np.linspace(0, 0.8, 17)
    rho = [D.merge_ratio_for(r) for r in ranks]
    keep = [(t[1] / t[0]) ** 2 for t in map(D.kv_tile_for, ranks)]
    assert all(a >= b for a, b in zip(rho, rho[1:])) and all(a <= b for a, b in zip(keep, keep[1:]))


def test_flat_profile_is_one_band():
    assert D.find_bands(np.full(12, 0.2)) == (0, 12)
    with pytest.raises(ValueError, match="NaN"):
        D.find_bands([0.1, float("nan")])


# ---------------------------------------------------------------------------------------
# maps
# ---------------------------------------------------------------------------------------


def coverage_closed_form(t: int, k: int, frames: int) -> float:
    """Covered fraction of the truncated grid by frames 0..S-1 of the phase-shifted
    (t, k) sub-grid, offsets ((f div t) mod t, f mod t): Q = S div t full row groups
    keep all t column phases on min(t, Q + k - 1) row phases; the R = S mod t frames of
    the next group add their column span min(t, R + k - 1) on the row phases they add
    (k when Q = 0, one when Q + k <= t, none beyond)."""
    q, rem = divmod(frames, t)
    covered = t * min(t, q + k - 1) if q else 0
    if rem:
        new_rows = k if q == 0 else (1 if q + k <= t else 0)
        covered += new_rows * min(t, rem + k - 1)
    return min(covered, t * t) / (t * t)


@pytest.mark.parametrize("tile", [(2, 1), (3, 2), (4, 3), (5, 3), (4, 1)])
def test_union_coverage_matches_the_closed_form(tile):
    t, k = tile
    for frames in range(1, t * t + 3):
        for h, w in ((2 * t, 3 * t), (2 * t + 1, 3 * t + 2)):  # the truncated grid, whatever the edges
            geom = Geometry(frames, h, w, 5)
            union, cov = D.union_coverage(geom, tile, True)
            assert cov == pytest.approx(coverage_closed_form(t, k, frames)), (tile, frames, h, w)
            assert not union[(h // t) * t:].any() and not union[:, (w // t) * t:].any()
        _, flat = D.union_coverage(Geometry(frames, 2 * t, 2 * t, 5), tile, False)
        assert flat == pytest.approx((k / t) ** 2)  # no phase shift: the same blind spots in every frame
    assert D.union_coverage(Geometry(t * t, 3 * t, 3 * t, 5), tile, True)[1] == 1.0


def test_kv_keep_maps_follow_the_preset():
    comp = make_compression("regime", 24)
    geom = Geometry(4, 6, 10, 5)
    tiles = D.kv_tiles(comp)
    assert sorted(tiles) == [(3, 2), (5, 3)] and tiles[(3, 2)] == list(range(10))
    keep = D.kv_keep_maps(comp, (3, 2), geom)
    assert keep.shape == (4, 6, 9 + 1) and keep[0].all()  # the anchor frame whole
    assert keep[1:, :, :9].mean() == pytest.approx(4 / 9) and not keep[1:, :, 9].any()
    no_anchor = D.kv_keep_maps(dataclasses.replace(comp, anchor=False), (3, 2), geom)
    assert no_anchor[0, :, :9].mean() == pytest.approx(4 / 9)


def test_merge_bands_show_the_layer_that_computes_each_bands_match():
    geom = Geometry(3, 6, 8, 5)
    regime = make_compression("regime", 24)
    assert D.merge_bands(regime, geom) == [("shallow", 0, list(range(10))), ("middle", 10, list(range(10, 18))),
                                           ("deep", 18, list(range(18, 24)))]
    # one cache band for the flanks: the deep band reuses the shallow band's match of L1
    one_cache = dataclasses.replace(regime, cache_band_starts=(0,), no_cache_layers=tuple(range(10, 18)))
    assert [(n, shown) for n, shown, _ in D.merge_bands(one_cache, geom)] == [
        ("shallow", 0), ("middle", 10), ("deep", 0)]
    assert D.merge_bands(make_compression("kv_only", 24), geom) == []


def test_psi_maps_and_protected_patches_are_the_forwards(tiny, golden):
    """Psi of the tiny fixture through the model's patch embed (the saliency the forward
    returns) -> maps on the 8 x 11 grid equal to upstream's [CLS] saliency, and the
    protected patches the top max(1, floor(0.1 * 88)) = 8 of every frame >= 1."""
    from rvggt_jax.model.patch_embed import patch_embed_tokens

    params, config = tiny
    images = jnp.asarray(golden["images"])
    psi = jax.jit(lambda p, x: patch_embed_tokens(p, x, config)[2])(params["aggregator"]["patch_embed"], images)
    b, s, _, hh, ww = images.shape
    h, w = hh // 14, ww // 14
    maps = np.asarray(D.saliency_maps(psi, h, w))
    assert maps.shape == (1, 3, h, w)
    assert np.array_equal(maps[0, 2, 3, 4], np.asarray(psi)[0, 2, 3 * w + 4])
    np.testing.assert_allclose(maps.reshape(1, 3, -1), golden["dino_cls_saliency"], rtol=1e-4, atol=1e-6)
    geom = Geometry(s, h, w, config.patch_start_idx)
    prot = np.asarray(D.protected_patches(make_compression("regime", 24), psi, geom))[0]
    assert not prot[0].any()
    for f in (1, 2):
        top = np.argsort(-np.asarray(psi)[0, f], kind="stable")[:8]
        assert sorted(np.flatnonzero(prot[f].ravel()).tolist()) == sorted(top.tolist())
    unprotected = dataclasses.replace(make_compression("regime", 24), protect="none")
    assert not np.asarray(D.protected_patches(unprotected, psi, geom)).any()
    assert not np.asarray(D.protected_patches(make_compression("dense", 24), psi, geom)).any()


# ---------------------------------------------------------------------------------------
# preset files
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PRESETS)
def test_every_preset_round_trips(tmp_path, name):
    for depth in (24, 2):
        comp = make_compression(name, depth)
        loaded = D.load_preset(D.save_preset(comp, tmp_path / f"{name}{depth}.json"), depth)
        assert loaded == comp and hash(loaded) == hash(comp)


def test_a_calibrated_preset_round_trips(tmp_path):
    comp, _ = D.propose(u_profile(9, 16))
    assert D.load_preset(D.save_preset(comp, tmp_path / "c.json")) == comp
    assert D.resolve_preset(str(tmp_path / "c.json"), 24) == comp
    assert D.resolve_preset("regime", 24) == make_compression("regime", 24)


def _write(path, doc):
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def test_bad_preset_files_say_what_is_wrong(tmp_path):
    good = json.loads(D.save_preset(make_compression("regime", 24), tmp_path / "r.json").read_text())

    def edit(**fields):
        return {**good, "compression": {**good["compression"], **fields}}

    cases = [
        (tmp_path / "missing.json", r"not found: .*missing\.json"),
        (_write(tmp_path / "bad.json", "{\"format\": "), r"bad\.json is not valid JSON: .* line 1"),
        (_write(tmp_path / "other.json", {"a": 1}), r"not an rvggt compression preset"),
        (_write(tmp_path / "top.json", {**good, "extra": 1}), r"unknown keys \['extra'\]"),
        (_write(tmp_path / "key.json", edit(merge_ratios=[0.5, 0.5, 0.5])), r"unknown keys \['merge_ratios'\]"),
        (_write(tmp_path / "cover.json", edit(merge_bands=[10, 30])), r"merge_bands \[10, 30\] do not cover the 24"),
        (_write(tmp_path / "order.json", edit(kv_bands=[14, 10])), r"kv_bands \[14, 10\] do not cover"),
        (_write(tmp_path / "layer.json", edit(no_cache_layers=[3, 24])), r"no_cache_layers holds \[24\]"),
        (_write(tmp_path / "rho.json", edit(merge_ratio=[0.5, 1.5, 0.5])), r"merge ratio must be in \[0, 1\)"),
        (_write(tmp_path / "len.json", edit(merge_ratio=[0.5, 0.5])), r"merge_ratio needs 3 per-band values"),
        (_write(tmp_path / "ver.json", {**good, "version": 9}), r"version 9 is not supported"),
    ]
    for path, message in cases:
        with pytest.raises(D.PresetError, match=message):
            D.load_preset(path)
    with pytest.raises(D.PresetError, match=r"written for 24 global layers; the model has 2"):
        D.load_preset(tmp_path / "r.json", depth=2)
    with pytest.raises(D.PresetError, match="unknown preset 'regim'"):
        D.resolve_preset("regim", 24)
    assert D.is_preset_path("x/regime") and D.is_preset_path("a.JSON") and not D.is_preset_path("regime")
    assert math.isfinite(D.load_preset(tmp_path / "r.json").alpha)
