"""The compressed global block against dense and against an independent float64
reference; each preset's shape plan; the cost model against the traced shapes; one
compilation per input shape."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.helpers import rel_err
from rvggt_jax.model import layers
from rvggt_jax.compression import PRESETS, Geometry, global_block, init_state, layer_plan, merge
from rvggt_jax.compression.partition import kv_static_keep, partition, stride_protected
from tests.helpers.compression_reference import (
    global_positions,
    kept_by_rule,
    random_block_params,
    reference_block,
    reference_match,
)
from rvggt_jax.config import DPTHeadConfig, VGGTConfig
from rvggt_jax.planning.cost import cost_report
from rvggt_jax.compression.plan import padded_head_dim

C, HEADS = 32, 2
S, H, W, NS = 4, 5, 7, 5
L = NS + H * W
N = S * L
BASE = VGGTConfig(embed_dim=C, num_heads=HEADS)
SHORT = VGGTConfig(embed_dim=C, num_heads=HEADS, depth=8, dpt_head=DPTHeadConfig(intermediate_layer_idx=(1, 3, 5, 7)))


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
    state = init_state(cfg.compression, sal, Geometry(S, H, W, NS))
    xd = xc = x
    for layer in range(24):
        xd = layers.sequence_block(block_params, xd, pos, layers.BlockConfig(HEADS, rope_freq=cfg.rope_freq))
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
         ("regime_paper", 0, dict(duplicate_protected=True)), ("fastvggt", 3, dict(duplicate_protected=True)),
         # the presets run their merging layers in two head groups (HEADS = 2); all heads at once:
         ("regime", 10, dict(merge_head_groups=1)), ("regime", 14, dict(merge_head_groups=1)),
         ("fastvggt", 3, dict(duplicate_protected=True, merge_head_groups=1))]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-L{c[1]}" + ("+" if len(c) > 2 else ""))
def test_block_equals_float64_reference(block_params, case):
    name, layer = case[0], case[1]
    cfg = BASE.with_compression(name, **(case[2] if len(case) > 2 else {}))
    cc = cfg.compression
    plan = layer_plan(cc, layer, Geometry(S, H, W, NS))
    assert plan.kind in ("merge", "kv")
    assert plan.kind == "kv" or plan.match == "compute"
    x, sal = _data(layer + 1)
    pos = global_positions(S, H, W)
    out, _ = jax.jit(lambda x, s: global_block(block_params, x, pos, layer, cfg, init_state(cfg.compression, s, Geometry(S, H, W, NS))))(x, sal)
    prot = _protected(cc, sal)
    keep = _kv_rule(cc, plan.tile, prot)
    part = partition(Geometry(S, H, W, NS), cc.dst_seed)
    xn = np.asarray(layers.layer_norm(block_params["norm1"], x), np.float64)
    for bi in range(x.shape[0]):
        if plan.kind == "kv":
            parent = np.arange(N)
        else:
            metric = np.asarray(x[bi], np.float64) if plan.metric == "input" else xn[bi]
            frame_of = None if cc.match_scope == "sequence" else np.arange(N) // L
            r = plan.r_max if cc.match_scope == "sequence" else plan.r_frame
            parent, (gap, second) = reference_match(metric, part.is_dst, prot[bi], r, frame_of)
            assert gap > 1e-5 and second > 1e-5
        extra = np.flatnonzero(prot[bi]) if cc.duplicate_protected and plan.kind == "merge" else None
        if extra is not None and cc.protect == "saliency":
            extra = np.asarray(init_state(cfg.compression, sal, Geometry(S, H, W, NS)).protected_pos[bi])
        if extra is not None:  # the authors duplicate only the protected dst
            extra = extra[part.is_dst[extra]]
        ref = reference_block(block_params, np.asarray(x[bi]), pos, HEADS, cfg.rope_freq, parent,
                              keep[bi] if plan.tile != (1, 1) else None, size_bias=cc.size_bias, extra_pos=extra)
        assert rel_err(out[bi], ref) <= 2e-5, (name, layer)


def test_head_groups_split_the_heads_into_contiguous_ranges():
    from rvggt_jax.compression.merged_layer import head_groups

    assert head_groups(16, 2) == (range(0, 8), range(8, 16))
    assert head_groups(5, 2) == (range(0, 2), range(2, 5))
    assert head_groups(1, 2) == (range(0, 1),)
    assert head_groups(3, 1) == (range(0, 3),)
    with pytest.raises(ValueError, match="merge_head_groups"):
        BASE.with_compression("regime", merge_head_groups=0)


@pytest.mark.parametrize("layer", [0, 10])
def test_head_groups_equal_all_heads_at_once(layer):
    """Three heads in two groups (1 + 2: unrolled) and in three (one loop over equal
    groups) give the output of all heads at once (merge_head_groups=1)."""
    c, heads = 48, 3
    p = random_block_params(jax.random.PRNGKey(1), c, heads)
    rng = np.random.default_rng(layer)
    x = jnp.asarray(rng.standard_normal((2, N, c)), jnp.float32)
    sal = jnp.asarray(rng.random((2, S, H * W)), jnp.float32)
    pos = global_positions(S, H, W)
    outs = []
    for groups in (1, 2, 3):
        cfg = VGGTConfig(embed_dim=c, num_heads=heads).with_compression("regime", merge_head_groups=groups)
        state = init_state(cfg.compression, sal, Geometry(S, H, W, NS))
        outs.append(jax.jit(lambda x: global_block(p, x, pos, layer, cfg, state)[0])(x))
    assert rel_err(outs[1], outs[0]) <= 1e-6 and rel_err(outs[2], outs[0]) <= 1e-6


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
    part = partition(Geometry(s, h, w, NS), cc.dst_seed)
    np.testing.assert_array_equal(np.flatnonzero(~part.is_dst), [19, 21, 22, 23, 24, 25])
    np.testing.assert_array_equal(stride_protected(n, cc.alpha), np.arange(0, 26, 2))
    duplicated = np.array([0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20])
    plan = layer_plan(cc, 0, Geometry(s, h, w, NS))
    # r = min(int(0.9 * 26), 6 src - 2 protected src) = 4: 19, 21, 23, 25 merge, 22 and 24 stay
    assert (plan.r, plan.n_unm, plan.n_query) == (4, 2, 22)
    # 13 protected, 11 of them dst: the rows and slots of their copies (stride: known statically)
    assert plan.n_dup_all == 13 and plan.n_dup == 11 == plan.expected_dup == duplicated.size and plan.masked

    x, sal = _data(7, s=s, h=h, w=w)  # stride protection ignores the saliency (its batch size only)
    pos = global_positions(s, h, w)
    state = init_state(cfg.compression, sal, Geometry(s, h, w, NS))
    out = jax.jit(lambda x: global_block(block_params, x, pos, 0, cfg, state)[0])(x)  # (compiled: faster than eager)
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


def test_protected_rows_hold_every_protected_token_once(block_params):
    """`duplicate_protected` where every unprotected src merges (regime's bands 0 and 2):
    the U unmerged rows are the protected tokens' own rows, in `protected_pos` order, and
    no duplicate rows or slots are added. The block's values are the float64 reference's
    (`test_block_equals_float64_reference`, regime layers 0 and 10 with duplicates)."""
    cfg = BASE.with_compression("regime", duplicate_protected=True)
    cc = cfg.compression
    geom = Geometry(S, H, W, NS)
    plan = layer_plan(cc, 0, geom)
    p_max = init_state(cc, _data(1)[1], geom).protected_pos.shape[1]  # (S - 1) frames' top patches
    assert plan.protected_rows and plan.n_dup == 0 and plan.r_max == plan.n_src
    assert plan.n_unm == p_max and plan.n_query == plan.n_dst + p_max
    assert plan.n_kv == plan.n_fixed + plan.n_dyn and plan.n_dyn == plan.n_unm
    # without duplicates, or with the paper's K/V protection, the layout stays
    assert not layer_plan(BASE.with_compression("regime").compression, 0, geom).protected_rows
    paper = layer_plan(BASE.with_compression("regime_paper", duplicate_protected=True).compression, 0, geom)
    assert not paper.protected_rows and paper.n_dup_all == p_max
    # 64 frames of 12 x 16: bands 0 and 2 merge every unprotected src, band 1 (rho 0.5) does not
    big = Geometry(64, 12, 16, NS)
    rows = {layer: layer_plan(cc, layer, big) for layer in (0, 10, 14, 18)}
    assert [rows[k].protected_rows for k in (0, 10, 14, 18)] == [True, False, False, True]
    assert (rows[0].n_query, rows[0].n_kv, rows[0].n_dup) == (4733, 2995, 0)
    # band 1: every protected token's copy listed, rows for 1.5x the expected protected dst
    assert (rows[10].n_query, rows[10].n_dup_all) == (6304, 1197) and 0 < rows[10].n_dup < 1197

    x, sal = _data(3)
    state = init_state(cc, sal, geom)
    protected_src = jnp.take(state.protected, plan.partition.src_pos, axis=1)
    xn = layers.layer_norm(block_params["norm1"], x)
    match = jax.jit(lambda m, ps, pp: merge.compute_match(m, ps, plan, 0, protected_pos=pp))(
        xn, protected_src, state.protected_pos)
    part = plan.partition
    for bi in range(x.shape[0]):
        pp = np.asarray(state.protected_pos[bi])
        np.testing.assert_array_equal(np.asarray(match.unm_pos[bi]), pp)
        np.testing.assert_array_equal(np.asarray(match.sizes[bi, plan.n_dst:]), 1.0)
        group = np.asarray(match.group[bi])
        own = plan.n_dst + np.arange(pp.size)
        src = ~part.is_dst[pp]
        np.testing.assert_array_equal(group[pp[src]], own[src])  # a protected src is its own row
        assert (group[pp[~src]] < plan.n_dst).all()  # a protected dst stays in its dst group
        # every unprotected src merged into a dst; each dst row's size counts its members
        unprotected_src = np.setdiff1d(part.src_pos, pp)
        assert (group[unprotected_src] < plan.n_dst).all()
        sizes = np.bincount(group[group < plan.n_dst], minlength=plan.n_dst)
        np.testing.assert_array_equal(np.asarray(match.sizes[bi, :plan.n_dst]), sizes)


def test_duplicate_capacity_branches_give_the_same_block(block_params):
    """Saliency protection with duplicates and no `protected_rows` (the paper variant's K/V
    protection): the copies get `n_dup` rows (`duplicate_capacity` times their expected
    count) and a sequence with more protected dst takes all `n_dup_all` (`lax.cond`).
    Capacity 0 (always the full branch), one that holds this data's protected dst (the
    short branch) and one of every protected token (no branch) give the same block; the
    float64 reference checks the default (`test_block_equals_float64_reference`)."""
    geom = Geometry(S, H, W, NS)
    x, sal = _data(1)
    pos = global_positions(S, H, W)
    base = BASE.with_compression("regime_paper", duplicate_protected=True)
    state = init_state(base.compression, sal, geom)
    part = partition(geom, base.compression.dst_seed)
    is_dst = part.is_dst[np.asarray(state.protected_pos)]  # [B, P]
    p_d = int(is_dst.sum(axis=1).max())
    # dst first: the rows beyond the protected dst are src
    assert all(np.array_equal(row, np.sort(row)[::-1]) for row in is_dst)
    outs, plans = {}, {}
    for cap in (0.0, 1e3):
        cfg = dataclasses.replace(base, compression=dataclasses.replace(base.compression, duplicate_capacity=cap))
        plans[cap] = layer_plan(cfg.compression, 0, geom)
        outs[cap] = jax.jit(lambda x, s, cfg=cfg: global_block(block_params, x, pos, 0, cfg,
                                                             init_state(cfg.compression, s, geom))[0])(x, sal)
    p = plans[0.0].n_dup_all
    assert plans[0.0].n_dup == 0 < p_d and plans[1e3].n_dup == p
    for cap in np.linspace(0.1, 4.0, 40):  # a capacity whose rows hold this data's protected dst, fewer than all
        cc = dataclasses.replace(base.compression, duplicate_capacity=float(cap))
        if p_d <= layer_plan(cc, 0, geom).n_dup < p:
            break
    else:
        pytest.skip("no capacity between this data's protected dst and all protected tokens")
    cfg = dataclasses.replace(base, compression=cc)
    outs["short"] = jax.jit(lambda x, s: global_block(block_params, x, pos, 0, cfg, init_state(cc, s, geom))[0])(x, sal)
    assert rel_err(outs[0.0], outs[1e3]) <= 1e-6 and rel_err(outs["short"], outs[1e3]) <= 1e-6
    assert cost_report(cfg, S, H * 14, W * 14)["layers"][0]["queries"] == plans[1e3].n_query + layer_plan(cc, 0, geom).n_dup


@pytest.mark.parametrize("duplicates", [False, True])
def test_kv_capacity_branches_give_the_same_block(block_params, duplicates):
    """A K/V-downsampled merging layer attends with `n_dyn_cap` dynamic slots
    (`kv_capacity` times their expected fill) and a sequence that fills more takes all
    `n_dyn` (`lax.cond`). Capacity 0 (always the full branch: this data fills some
    slots), one that holds this data's filled slots (the short branch) and one past the
    bound (no branch) give the same block, with and without the authors' duplicates
    (whose own capacity branch composes with this one); the float64 reference checks
    the default (`test_block_equals_float64_reference`)."""
    geom = Geometry(S, H, W, NS)
    x, sal = _data(0)  # (fills 4 and 1 of the 9 dynamic slots of layer 0)
    pos = global_positions(S, H, W)
    base = BASE.with_compression("regime", duplicate_protected=duplicates)

    def run(cap):
        cfg = dataclasses.replace(base, compression=dataclasses.replace(base.compression, kv_capacity=float(cap)))
        return cfg, jax.jit(lambda x, s: global_block(block_params, x, pos, 0, cfg,
                                                      init_state(cfg.compression, s, geom)))(x, sal)

    plan = layer_plan(base.compression, 0, geom)
    assert plan.kv_mode == "select" and plan.n_dyn > 0
    outs = {}
    for cap in (1e3, 0.0):
        cfg, (outs[cap], state) = run(cap)
        p = layer_plan(cfg.compression, 0, geom)
        assert (p.n_dyn_cap == 0) if cap == 0 else (p.n_dyn_cap == p.n_dyn)
    (_, ok), = state.kv.values()
    filled = int(np.asarray(ok).sum(axis=1).max())
    assert 0 < filled < plan.n_dyn
    for cap in np.linspace(0.1, 6.0, 60):  # a capacity that holds this data's filled slots, short of all
        p = layer_plan(dataclasses.replace(base.compression, kv_capacity=float(cap)), 0, geom)
        if filled <= p.n_dyn_cap < p.n_dyn:
            break
    else:
        pytest.skip("no capacity between this data's filled slots and the bound")
    cfg, (outs["short"], _) = run(cap)
    assert rel_err(outs[0.0], outs[1e3]) <= 1e-6 and rel_err(outs["short"], outs[1e3]) <= 1e-6
    row = cost_report(cfg, S, H * 14, W * 14)["layers"][0]
    assert row["kv_slots"] == plan.n_fixed + p.n_dyn_cap + plan.n_dup and row["kv_dynamic_bound"] == plan.n_dyn


def test_frame_layers_attend_within_each_frame(block_params):
    cfg = BASE.with_compression("avggt")
    x, sal = _data(4)
    pos = global_positions(S, H, W)
    out, _ = global_block(block_params, x, pos, 3, cfg, init_state(cfg.compression, sal, Geometry(S, H, W, NS)))
    ref = layers.sequence_block(block_params, x.reshape(2 * S, L, C), pos[:, :L],
                                 layers.BlockConfig(HEADS, rope_freq=cfg.rope_freq)).reshape(2, N, C)
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
    p0, p10, p14, p18 = (layer_plan(cc, i, Geometry(S, H, W, NS)) for i in (0, 10, 14, 18))
    # N = 160, dst = 40 + 3 * (5 + 12) = 91, src = 3 * 23 = 69, kp = 3 -> r <= 60
    assert (p0.tokens, p0.n_dst, p0.n_src, p0.r, p0.n_unm, p0.n_query) == (160, 91, 69, 60, 9, 100)
    assert (p10.r, p10.n_query, p10.kv_mode, p10.n_kv, p10.metric) == (60, 100, "all", 100, "norm1")
    assert (p14.r, p14.tile, p18.r, p18.tile) == (60, (5, 3), 60, (5, 3))
    # rho = 0.5: r = min(80, 60) = 60 here; with 12 x 16 and S = 64 the ratio binds
    big = layer_plan(cc, 10, Geometry(64, 12, 16, NS))
    assert big.r == int(0.5 * 64 * 197) == 6304 and big.n_query == 64 * 197 - 6304
    part = partition(Geometry(S, H, W, NS), cc.dst_seed)
    keep = kv_static_keep(Geometry(S, H, W, NS), (3, 2), True, True)
    assert p0.n_fixed == keep[part.dst_pos].sum()
    assert p0.n_dyn == min(p0.n_unm, keep[part.src_pos].sum())
    assert p0.n_kv == p0.n_fixed + p0.n_dyn and p0.masked and p0.size_column


@pytest.mark.parametrize("name", PRESETS)
def test_shape_plan_of_every_preset(name):
    cfg = BASE.with_compression(name)
    cc = cfg.compression
    for layer in range(24):
        plan = layer_plan(cc, layer, Geometry(S, H, W, NS))
        kind = cc.layer_kind(layer)
        if kind in ("dense", "frame"):
            assert plan.kind == kind and plan.n_query == N
            continue
        n, n_dst, n_src, r = _expected_plan(cc, layer)
        if cc.protect == "stride":
            is_src = ~partition(Geometry(S, H, W, NS), cc.dst_seed).is_dst
            r = min(int(n * cc.layer_merge_ratio(layer)), n_src - int(is_src[stride_protected(n, cc.alpha)].sum()))
        if cc.match_scope == "frame":
            cells = -(-H // 2) * -(-W // 2)
            r = (S - 1) * min(int(L * cc.layer_merge_ratio(layer)), H * W - cells - max(1, int(cc.alpha * H * W)))
        tile = cc.layer_tile(layer)
        if r == 0 and tile == (1, 1):
            assert plan.kind == "dense"
        elif r == 0:
            assert plan.kind == "kv" and plan.n_query == N
            assert plan.n_kv == kv_static_keep(Geometry(S, H, W, NS), tile, cc.phase_shift, cc.anchor).sum() + plan.n_dyn
        else:
            assert plan.kind == "merge" and plan.r == r and plan.n_query == n - r
            assert plan.n_dst == n_dst and plan.n_unm == n_src - r
            if tile == (1, 1):
                assert plan.n_kv == plan.n_query
            else:
                assert plan.n_fixed + plan.n_dyn + plan.n_dup == plan.n_kv <= plan.n_query


def _stack(params, x, sal, cfg, s, h, w):
    pos = global_positions(s, h, w)
    state = init_state(cfg.compression, sal, Geometry(s, h, w, NS))
    for layer in range(cfg.depth):
        x, state = global_block(params, x, pos, layer, cfg, state)
    return x


@pytest.mark.parametrize("name", ["regime", "regime_paper", "regime_local", "fastvggt", "avggt", "kv_only"])
def test_cost_model_agrees_with_traced_shapes(name, block_params):
    # The block checks, while it is traced, that its attention has the plan's queries, K/V
    # slots and folded head dim (a mismatch raises): tracing the stack and reading the
    # cost report, which prices those same plans, compares the two.
    s, h, w = 6, 6, 9
    cfg = VGGTConfig(embed_dim=64, num_heads=2).with_compression(name)
    x = jax.ShapeDtypeStruct((1, s * (NS + h * w), 64), jnp.float32)
    sal = jax.ShapeDtypeStruct((1, s, h * w), jnp.float32)
    params = random_block_params(jax.random.PRNGKey(1), 64, 2)
    jax.eval_shape(lambda x, sl: _stack(params, x, sl, cfg, s, h, w), x, sal)
    report = cost_report(cfg, s, h * 14, w * 14)
    assert len(report["layers"]) == 24
    geom, d = Geometry(s, h, w, NS), 32
    for row in report["layers"]:
        plan = layer_plan(cfg.compression, row["layer"], geom)
        if plan.kind in ("dense", "frame"):
            want = (plan.n_query, plan.n_kv, d) if plan.kind == "dense" else (plan.per_frame, plan.per_frame, d)
        else:
            # (the K/V slots a sequence attends with unless it fills more: the capacity)
            want = (plan.n_query, plan.n_kv - plan.n_dyn + plan.n_dyn_cap,
                    padded_head_dim(d, plan.size_column, cfg.compression.head_pad_multiple))
        assert (row["queries"], row["kv_slots"], row["head_dim_qk"]) == want, (name, row["layer"])


def test_block_refuses_shapes_that_differ_from_its_plan(block_params, monkeypatch):
    # the trace-time check the cost model relies on: a plan that promises one K/V slot
    # more than the block builds is an error
    from rvggt_jax.compression import block as block_mod

    cfg = BASE.with_compression("regime")
    geom = Geometry(S, H, W, NS)
    x, sal = _data()
    pos = global_positions(S, H, W)
    state = init_state(cfg.compression, sal, geom)
    # (traced, not run: the check is at trace time)
    jax.eval_shape(lambda x: global_block(block_params, x, pos, 0, cfg, state)[0], x)  # the true plan passes
    true_plan = layer_plan
    monkeypatch.setattr(block_mod, "layer_plan",
                        lambda comp, layer, g: dataclasses.replace(true_plan(comp, layer, g),
                                                                   n_fixed=true_plan(comp, layer, g).n_fixed + 1))
    with pytest.raises(AssertionError, match="the plan says"):
        jax.eval_shape(lambda x: global_block(block_params, x, pos, 0, cfg, state)[0], x)


def test_global_block_computes_its_static_plan_once(block_params):
    # one call of a merging block reads its plan (`layer_plan`, cached: no Python call
    # into plan.py) and never enters partition.py: the plan carries the partition and
    # the K/V masks (it used to enter partition.py 8 times and plan.py 7 times)
    import sys

    cfg = BASE.with_compression("regime_paper", duplicate_protected=True)
    geom = Geometry(S, H, W, NS)
    x, sal = _data()
    pos = global_positions(S, H, W)
    state = init_state(cfg.compression, sal, geom)
    layer_plan(cfg.compression, 0, geom)  # computed (and cached) before the block runs
    calls = {"plan.py": [], "partition.py": []}

    def count(frame, event, arg):  # Python functions of the two modules (not Geometry's properties)
        if event == "call" and not frame.f_code.co_qualname.startswith("Geometry."):
            name = frame.f_code.co_filename
            for key in calls:
                if name.endswith("compression/" + key):
                    calls[key].append(frame.f_code.co_qualname)

    sys.setprofile(count)
    try:
        jax.eval_shape(lambda x: global_block(block_params, x, pos, 0, cfg, state)[0], x)
    finally:
        sys.setprofile(None)
    # (check_shapes, padded_head_dim: the block's check of its attention's shapes against
    # the plan)
    assert not calls["partition.py"] and set(calls["plan.py"]) <= {"check_shapes", "padded_head_dim"}, calls


@pytest.mark.parametrize("name", ["regime", "regime_paper", "fastvggt", "avggt"])
def test_one_compilation_per_input_shape(block_params, name):
    # (every preset through the whole model: tests/compression/test_e2e.py)
    s, h, w = 3, 4, 5
    x1, sal1 = _data(1, 1, s, h, w)
    x2, sal2 = _data(2, 1, s, h, w)
    # an 8-layer stack: make_compression rescales the 24-layer bands, and every kind of band
    # is still in it (for regime: a match computed at 0 and reused to 3, merge-only layer 4
    # recomputing, a K/V band at 5, a cache from 6), at a third of the unrolled compile
    cfg = SHORT.with_compression(name)
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
    # patches are keys, in the plans the block runs (it checks its shapes against them)
    s, h, w = 4, 15, 15
    cfg = VGGTConfig(embed_dim=32, num_heads=2).with_compression("kv_only", anchor=False)
    x = jax.ShapeDtypeStruct((1, s * (NS + h * w), 32), jnp.float32)
    sal = jax.ShapeDtypeStruct((1, s, h * w), jnp.float32)
    jax.eval_shape(lambda x, sl: _stack(block_params, x, sl, cfg, s, h, w), x, sal)
    plans = [layer_plan(cfg.compression, i, Geometry(s, h, w, NS)) for i in range(24)]
    assert plans[0].n_kv == s * NS + s * h * w * 4 // 9  # (3, 2): 4/9
    assert plans[12].n_kv == s * (NS + h * w)  # merge-only layers: everything
    assert plans[20].n_kv == s * NS + s * h * w * 9 // 25  # (5, 3): 9/25
    assert all(plan.n_query == s * (NS + h * w) for plan in plans)
