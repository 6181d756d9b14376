"""The compressed global block against dense and against an independent float64
reference; each preset's shape plan; the cost model against the traced shapes; one
compilation per input shape."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import rel_err
from rvggt_jax import layers
from rvggt_jax.compression import PRESETS, global_block, init_state, layer_plan, record_shapes
from rvggt_jax.compression.partition import kv_static_keep, partition, stride_protected
from tests._compression_reference import (
    global_positions,
    kept_by_rule,
    random_block_params,
    reference_block,
    reference_match,
)
from rvggt_jax.config import VGGTConfig
from rvggt_jax.cost import cost_report

C, HEADS = 32, 2
S, H, W, NS = 4, 5, 7, 5
L = NS + H * W
N = S * L
BASE = VGGTConfig(embed_dim=C, num_heads=HEADS)


@pytest.fixture(scope="module")
def block_params():
    return random_block_params(jax.random.PRNGKey(0), C, HEADS)


def _data(seed=0, b=2, s=S, h=H, w=W):
    rng = np.random.default_rng(seed)
    n = s * (NS + h * w)
    x = rng.standard_normal((b, n, C)).astype(np.float32)
    sal = rng.random((b, s, h * w)).astype(np.float32)
    return jnp.asarray(x), jnp.asarray(sal)


def test_rho0_sigma1_equals_dense(block_params):
    cfg = BASE.with_compression("regime", merge_ratio=(0.0, 0.0, 0.0), kv_sigma=(1.0, 1.0, 1.0))
    x, sal = _data()
    pos = global_positions(S, H, W)
    state = init_state(cfg, sal, S, (H, W))
    xd = xc = x
    for layer in range(24):
        xd = layers.block(block_params, xd, HEADS, pos, cfg.rope_freq)
        xc, state = global_block(block_params, xc, pos, layer, cfg, state)
    assert rel_err(xc, xd) <= 1e-5


def _kv_rule(cc, tile, protected):
    """[B, N] kept-as-K/V by parent position, written out from the rule."""
    keep = np.zeros((protected.shape[0], N), bool)
    for n in range(N):
        f, loc = divmod(n, L)
        if loc < NS or (cc.anchor and f == 0):
            keep[:, n] = True
            continue
        i, j = divmod(loc - NS, W)
        keep[:, n] = kept_by_rule(f, i, j, H, W, tile, cc.phase_shift)
    if cc.kv_protect_saliency and tile != (1, 1):
        keep |= protected
    return keep


def _protected(cc, sal):
    b = sal.shape[0]
    flags = np.zeros((b, N), bool)
    if cc.protect == "saliency":
        kp = max(1, int(cc.alpha * H * W))
        for bi in range(b):
            for f in range(1, S):
                flags[bi, f * L + NS + np.argsort(-np.asarray(sal[bi, f]), kind="stable")[:kp]] = True
    elif cc.protect == "stride":
        flags[:, stride_protected(N, cc.alpha)] = True
    return flags


CASES = [("regime", 0), ("regime", 10), ("regime", 14), ("regime", 18), ("regime_paper", 12), ("regime_paper", 0),
         ("regime_local", 0), ("regime_local", 14), ("fastvggt", 5), ("no_anchor", 0), ("no_phase_shift", 14),
         ("no_size_bias", 0), ("kv_only", 0), ("avggt", 12), ("merge_only", 0),
         ("regime", 0, dict(merge_ratio=(0.3, 0.3, 0.3))), ("regime", 0, dict(kv_sigma=(2, 2, 2))),
         ("regime", 0, dict(duplicate_protected=True)), ("regime", 10, dict(duplicate_protected=True)),
         ("regime_paper", 0, dict(duplicate_protected=True)), ("fastvggt", 3, dict(duplicate_protected=True))]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-L{c[1]}" + ("+" if len(c) > 2 else ""))
def test_block_equals_float64_reference(block_params, case):
    name, layer = case[0], case[1]
    cfg = BASE.with_compression(name, **(case[2] if len(case) > 2 else {}))
    cc = cfg.compression
    plan = layer_plan(cc, layer, S, H, W, NS)
    assert plan.kind in ("merge", "kv")
    assert plan.kind == "kv" or plan.match == "compute"
    x, sal = _data(layer + 1)
    pos = global_positions(S, H, W)
    out, _ = jax.jit(lambda x, s: global_block(block_params, x, pos, layer, cfg, init_state(cfg, s, S, (H, W))))(x, sal)
    prot = _protected(cc, sal)
    keep = _kv_rule(cc, plan.tile, prot)
    part = partition(S, H, W, NS, cc.dst_seed)
    xn = np.asarray(layers.layer_norm(block_params["norm1"], x), np.float64)
    for bi in range(x.shape[0]):
        if plan.kind == "kv":
            parent = np.arange(N)
        else:
            metric = np.asarray(x[bi], np.float64) if plan.metric == "input" else xn[bi]
            frame_of = None if cc.match_scope == "sequence" else np.arange(N) // L
            r = plan.r if cc.match_scope == "sequence" else plan.r_frame
            parent, (gap, second) = reference_match(metric, part.is_dst, prot[bi], r, frame_of)
            assert gap > 1e-5 and second > 1e-5
        extra = np.flatnonzero(prot[bi]) if cc.duplicate_protected and plan.kind == "merge" else None
        if extra is not None and cc.protect == "saliency":
            extra = np.asarray(init_state(cfg, sal, S, (H, W))["protected_pos"][bi])
        if extra is not None:  # the authors duplicate only the protected dst
            extra = extra[part.is_dst[extra]]
        ref = reference_block(block_params, np.asarray(x[bi]), pos, HEADS, cfg.rope_freq, parent,
                              keep[bi] if plan.tile != (1, 1) else None, size_bias=cc.size_bias, extra_pos=extra)
        assert rel_err(out[bi], ref) <= 2e-5, (name, layer)


def test_duplicate_protected_duplicates_only_protected_dst(block_params):
    """Hand-computed: 2 frames of 2 x 4 patches (+5 special tokens each), N = 26.
    dst (seed -1: top-left of each 2 x 2 cell) = frame 0 (0-12), frame 1's specials
    (13-17) and patches 18, 20; src = 19, 21-25. Stride protection with alpha 0.5 protects
    13 tokens at stride 2: 0, 2, ..., 24. Of these, 22 and 24 are src: the authors drop
    them from both the merged and the unmerged lists (they are kept, once), so only the
    11 protected dst 0, 2, ..., 20 come a second time among the keys."""
    s, h, w = 2, 2, 4
    n = s * (NS + h * w)
    cfg = BASE.with_compression("fastvggt", alpha=0.5, dst_seed=-1, duplicate_protected=True)
    cc = cfg.compression
    part = partition(s, h, w, NS, cc.dst_seed)
    np.testing.assert_array_equal(np.flatnonzero(~part.is_dst), [19, 21, 22, 23, 24, 25])
    np.testing.assert_array_equal(stride_protected(n, cc.alpha), np.arange(0, 26, 2))
    duplicated = np.array([0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20])
    plan = layer_plan(cc, 0, s, h, w, NS)
    # r = min(int(0.9 * 26), 6 src - 2 protected src) = 4: 19, 21, 23, 25 merge, 22 and 24 stay
    assert (plan.r, plan.n_unm, plan.n_query) == (4, 2, 22)
    assert plan.n_dup == 13 and plan.expected_dup == duplicated.size and plan.masked

    x, sal = _data(7, s=s, h=h, w=w)  # stride protection ignores the saliency (its batch size only)
    pos = global_positions(s, h, w)
    out, _ = global_block(block_params, x, pos, 0, cfg, init_state(cfg, sal, s, (h, w)))
    protected = np.zeros(n, bool)
    protected[stride_protected(n, cc.alpha)] = True
    xn = np.asarray(layers.layer_norm(block_params["norm1"], x), np.float64)
    for bi in range(x.shape[0]):
        parent, _ = reference_match(xn[bi], part.is_dst, protected, plan.r)
        assert (parent[[22, 24]] == [22, 24]).all() and (parent[[19, 21, 23, 25]] != [19, 21, 23, 25]).all()
        ref = reference_block(block_params, np.asarray(x[bi]), pos, HEADS, cfg.rope_freq, parent, None,
                              size_bias=False, extra_pos=duplicated)
        assert rel_err(out[bi], ref) <= 2e-5
        # every protected token duplicated (the old behaviour) is a different block
        every = reference_block(block_params, np.asarray(x[bi]), pos, HEADS, cfg.rope_freq, parent, None,
                                size_bias=False, extra_pos=np.arange(0, 26, 2))
        assert rel_err(out[bi], every) > 1e-3


def test_frame_layers_attend_within_each_frame(block_params):
    cfg = BASE.with_compression("avggt")
    x, sal = _data(4)
    pos = global_positions(S, H, W)
    out, _ = global_block(block_params, x, pos, 3, cfg, init_state(cfg, sal, S, (H, W)))
    ref = layers.block(block_params, x.reshape(2 * S, L, C), HEADS, pos[:, :L], cfg.rope_freq).reshape(2, N, C)
    np.testing.assert_array_equal(out, ref)


def _expected_plan(cc, layer, s=S, h=H, w=W):
    """Counts derived by hand from the spec (independent of plan.py)."""
    L_ = NS + h * w
    n = s * L_
    cells = -(-h // 2) * -(-w // 2)
    n_dst = L_ + (s - 1) * (NS + cells)
    n_src = (s - 1) * (h * w - cells)
    kp = max(1, int(cc.alpha * h * w))
    rho = cc.layer_merge_ratio(layer)
    r = min(int(n * rho), n_src - (s - 1) * kp) if rho > 0 else 0
    return n, n_dst, n_src, r


def test_shape_plan_exact_regime_small_grid():
    cc = BASE.with_compression("regime").compression
    p0, p10, p14, p18 = (layer_plan(cc, i, S, H, W, NS) for i in (0, 10, 14, 18))
    # N = 160, dst = 40 + 3 * (5 + 12) = 91, src = 3 * 23 = 69, kp = 3 -> r <= 60
    assert (p0.tokens, p0.n_dst, p0.n_src, p0.r, p0.n_unm, p0.n_query) == (160, 91, 69, 60, 9, 100)
    assert (p10.r, p10.n_query, p10.kv_mode, p10.n_kv, p10.metric) == (60, 100, "all", 100, "norm1")
    assert (p14.r, p14.tile, p18.r, p18.tile) == (60, (5, 3), 60, (5, 3))
    # rho = 0.5: r = min(80, 60) = 60 here; with 12 x 16 and S = 64 the ratio binds
    big = layer_plan(cc, 10, 64, 12, 16, NS)
    assert big.r == int(0.5 * 64 * 197) == 6304 and big.n_query == 64 * 197 - 6304
    part = partition(S, H, W, NS, cc.dst_seed)
    keep = kv_static_keep(S, H, W, NS, (3, 2), True, True)
    assert p0.n_fixed == keep[part.dst_pos].sum()
    assert p0.n_dyn == min(p0.n_unm, keep[part.src_pos].sum())
    assert p0.n_kv == p0.n_fixed + p0.n_dyn and p0.masked and p0.size_column


@pytest.mark.parametrize("name", PRESETS)
def test_shape_plan_of_every_preset(name):
    cfg = BASE.with_compression(name)
    cc = cfg.compression
    for layer in range(24):
        plan = layer_plan(cc, layer, S, H, W, NS)
        kind = cc.layer_kind(layer)
        if kind in ("dense", "frame"):
            assert plan.kind == kind and plan.n_query == N
            continue
        n, n_dst, n_src, r = _expected_plan(cc, layer)
        if cc.protect == "stride":
            is_src = ~partition(S, H, W, NS, cc.dst_seed).is_dst
            r = min(int(n * cc.layer_merge_ratio(layer)), n_src - int(is_src[stride_protected(n, cc.alpha)].sum()))
        if cc.match_scope == "frame":
            cells = -(-H // 2) * -(-W // 2)
            r = (S - 1) * min(int(L * cc.layer_merge_ratio(layer)), H * W - cells - max(1, int(cc.alpha * H * W)))
        tile = cc.layer_tile(layer)
        if r == 0 and tile == (1, 1):
            assert plan.kind == "dense"
        elif r == 0:
            assert plan.kind == "kv" and plan.n_query == N
            assert plan.n_kv == kv_static_keep(S, H, W, NS, tile, cc.phase_shift, cc.anchor).sum() + plan.n_dyn
        else:
            assert plan.kind == "merge" and plan.r == r and plan.n_query == n - r
            assert plan.n_dst == n_dst and plan.n_unm == n_src - r
            if tile == (1, 1):
                assert plan.n_kv == plan.n_query
            else:
                assert plan.n_fixed + plan.n_dyn + plan.n_dup == plan.n_kv <= plan.n_query


def _stack(params, x, sal, cfg, s, h, w):
    pos = global_positions(s, h, w)
    state = init_state(cfg, sal, s, (h, w))
    for layer in range(cfg.depth):
        x, state = global_block(params, x, pos, layer, cfg, state)
    return x


@pytest.mark.parametrize("name", ["regime", "regime_paper", "regime_local", "fastvggt", "avggt", "kv_only"])
def test_cost_model_agrees_with_traced_shapes(name, block_params):
    s, h, w = 6, 6, 9
    cfg = VGGTConfig(embed_dim=64, num_heads=2).with_compression(name)
    x = jax.ShapeDtypeStruct((1, s * (NS + h * w), 64), jnp.float32)
    sal = jax.ShapeDtypeStruct((1, s, h * w), jnp.float32)
    params = random_block_params(jax.random.PRNGKey(1), 64, 2)
    with record_shapes() as log:
        jax.eval_shape(lambda x, sl: _stack(params, x, sl, cfg, s, h, w), x, sal)
    report = cost_report(cfg, s, h * 14, w * 14)
    assert len(log) == 24
    for row, traced in zip(report["layers"], log):
        assert row["layer"] == traced["layer"]
        assert (row["queries"], row["kv_slots"], row["head_dim_qk"]) == (
            traced["queries"], traced["kv"], traced["head_dim"]), (name, row["layer"])


@pytest.mark.parametrize("name", ["regime", "regime_paper", "fastvggt", "avggt"])
def test_one_compilation_per_input_shape(block_params, name):
    # (every preset through the whole model: tests/test_compression_e2e.py)
    s, h, w = 3, 4, 5
    x1, sal1 = _data(1, 1, s, h, w)
    x2, sal2 = _data(2, 1, s, h, w)
    cfg = BASE.with_compression(name)
    traces = []

    def fwd(x, sl, cfg=cfg):
        traces.append(1)
        return _stack(block_params, x, sl, cfg, s, h, w)

    f = jax.jit(fwd)
    a = f(x1, sal1)
    b = f(x2, sal2)
    assert len(traces) == 1 and f._cache_size() == 1, name
    assert np.isfinite(np.asarray(a)).all() and np.isfinite(np.asarray(b)).all(), name
    assert not np.allclose(a, b)
    # shapes never depend on data: the same trace for a saliency with ties everywhere
    jax.block_until_ready(f(x1, jnp.zeros_like(sal1)))
    assert len(traces) == 1


def test_kept_kv_fraction_per_band_with_merging_off(block_params):
    # grid 15 x 15 is a multiple of t = 3 and t = 5: per non-anchor frame (k/t)^2 of the
    # patches are keys, in the shapes the block really uses.
    s, h, w = 4, 15, 15
    cfg = VGGTConfig(embed_dim=32, num_heads=2).with_compression("kv_only", anchor=False)
    x = jax.ShapeDtypeStruct((1, s * (NS + h * w), 32), jnp.float32)
    sal = jax.ShapeDtypeStruct((1, s, h * w), jnp.float32)
    with record_shapes() as log:
        jax.eval_shape(lambda x, sl: _stack(block_params, x, sl, cfg, s, h, w), x, sal)
    kv = {row["layer"]: row["kv"] for row in log}
    assert kv[0] == s * NS + s * h * w * 4 // 9  # (3, 2): 4/9
    assert kv[12] == s * (NS + h * w)  # merge-only layers: everything
    assert kv[20] == s * NS + s * h * w * 9 // 25  # (5, 3): 9/25
    assert all(row["queries"] == s * (NS + h * w) for row in log)
