"""Matching, merge / unmerge, sizes, protection and the band cache."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.compression import kv as kv_lib
from rvggt_jax.compression import make_compression
from rvggt_jax.compression import matching
from rvggt_jax.compression import merge as merge_lib
from rvggt_jax.compression.partition import Geometry, partition, stride_protected
from rvggt_jax.compression.plan import layer_plan
from rvggt_jax.compression.state import init_state
from tests.helpers.compression_reference import identity_match, reference_match

S, H, W, NS = 4, 5, 7, 5
L = NS + H * W
N = S * L


def _inputs(seed=0, b=2):
    rng = np.random.default_rng(seed)
    metric = rng.standard_normal((b, N, 16)).astype(np.float32)
    sal = rng.random((b, S, H * W)).astype(np.float32)
    return metric, sal


def _protected(sal, kp):
    b = sal.shape[0]
    flags = np.zeros((b, N), bool)
    for bi in range(b):
        for f in range(1, S):
            top = np.argsort(-sal[bi, f], kind="stable")[:kp]
            flags[bi, f * L + NS + top] = True
    return flags


def _parents(match, part, plan):
    """parent position of every token from a match (dst position of its group)."""
    group = np.asarray(match.group)
    layout = np.concatenate([np.broadcast_to(part.dst_pos, (group.shape[0], plan.n_dst)),
                             np.asarray(match.unm_pos)], axis=1)
    return np.take_along_axis(layout, group, axis=1)


@pytest.mark.parametrize("scope", ["sequence", "frame"])
@pytest.mark.parametrize("rho", [0.3, 0.6, 0.99])
def test_match_equals_reference(scope, rho):
    cc = make_compression("regime", 24, merge_ratio=(rho, rho, rho), match_scope=scope, dst_seed=7)
    plan = layer_plan(cc, 0, Geometry(S, H, W, NS))
    part = partition(Geometry(S, H, W, NS), cc.dst_seed)
    metric, sal = _inputs()
    prot = _protected(sal, plan.protect_per_frame)
    match = jax.jit(lambda m, p: merge_lib.compute_match(m, p, plan, 64))(
        jnp.asarray(metric), jnp.asarray(prot[:, part.src_pos]))
    parents = _parents(match, part, plan)
    for bi in range(metric.shape[0]):
        frame_of = None if scope == "sequence" else np.arange(N) // L
        r = plan.r_max if scope == "sequence" else plan.r_frame
        ref, (gap, second) = reference_match(metric[bi].astype(np.float64), part.is_dst, prot[bi], r, frame_of)
        assert gap > 1e-5 and second > 1e-5  # no near-ties on this data
        np.testing.assert_array_equal(parents[bi], ref)
    # static counts
    assert match.group.shape == (2, N) and match.sizes.shape == (2, plan.n_query)
    assert match.unm_pos.shape == (2, plan.n_unm)
    assert plan.n_query == N - plan.r


def test_protected_never_merged_and_sizes_count_groups():
    cc = make_compression("regime", 24)
    plan = layer_plan(cc, 0, Geometry(S, H, W, NS))
    part = partition(Geometry(S, H, W, NS), cc.dst_seed)
    metric, sal = _inputs(3)
    prot = _protected(sal, plan.protect_per_frame)
    match = merge_lib.compute_match(jnp.asarray(metric), jnp.asarray(prot[:, part.src_pos]), plan, 0)
    parents = _parents(match, part, plan)
    group = np.asarray(match.group)
    sizes = np.asarray(match.sizes)
    for bi in range(2):
        assert (parents[bi][prot[bi]] == np.flatnonzero(prot[bi])).all()  # protected stay themselves
        np.testing.assert_array_equal(np.bincount(group[bi], minlength=plan.n_query), sizes[bi])
        assert sizes[bi].sum() == N
        merged_src = (parents[bi] != np.arange(N))
        # the authors' count: every unprotected src (rho 0.99), more than the static r by
        # the protected dst; their rows of the static layout are empty
        unprotected_src = int((~part.is_dst & ~prot[bi]).sum())
        assert plan.r < plan.r_max and merged_src.sum() == min(plan.r_max, unprotected_src) > plan.r
        assert (sizes[bi] == 0).sum() == merged_src.sum() - plan.r
        assert part.is_dst[parents[bi][merged_src]].all()  # merged into dst only
        assert (~part.is_dst[merged_src]).all()  # only src merge


@pytest.mark.parametrize("alpha", [0.1, 0.3])
def test_stride_protected_src_are_not_matched(alpha):
    """Under stride protection (FastVGGT) the protected src are static and never merge:
    the plan matches only the others (`LayerPlan.matched_src`), and the match equals the
    one computed over every src (protected scores and args then unused)."""
    geom = Geometry(S, H, W, NS)
    cc = make_compression("fastvggt", 24, alpha=alpha)
    plan = layer_plan(cc, 3, geom)
    part = partition(geom, cc.dst_seed)
    prot_src = np.isin(part.src_pos, stride_protected(N, alpha))
    assert prot_src.any() and plan.matched_src is not None
    np.testing.assert_array_equal(plan.matched_src, np.flatnonzero(~prot_src))
    assert plan.r <= plan.matched_src.size and plan.match_pairs == plan.matched_src.size * plan.n_dst
    metric, _ = _inputs(5)
    protected = init_state(cc, None, geom).protected
    protected_src = jnp.take(protected, part.src_pos, axis=1)
    np.testing.assert_array_equal(np.asarray(protected_src[0]), prot_src)
    # (eager: the two plans compare equal, so a jit would reuse one program for both)
    got = merge_lib.compute_match(jnp.asarray(metric[:1]), protected_src, plan, 0)
    want = merge_lib.compute_match(jnp.asarray(metric[:1]), protected_src, dataclasses.replace(plan, matched_src=None), 0)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    # saliency protection is data: every src is matched
    assert layer_plan(make_compression("regime", 24), 0, geom).matched_src is None


def test_merge_unmerge_identity_and_group_outputs():
    x = jnp.asarray(np.random.default_rng(1).standard_normal((2, N, 6)), jnp.float32)
    ident = identity_match(N, 2)
    np.testing.assert_array_equal(merge_lib.unmerge(merge_lib.merge(x, ident, N), ident.group), x)

    cc = make_compression("regime", 24, merge_ratio=(0.7, 0.7, 0.7))
    plan = layer_plan(cc, 0, Geometry(S, H, W, NS))
    match = merge_lib.compute_match(x, None, plan, 0)
    m = merge_lib.merge(x, match, plan.n_query)
    group = np.asarray(match.group)
    xs = np.asarray(x)
    for bi in range(2):
        for g in range(plan.n_query):
            members = xs[bi][group[bi] == g]
            # (no protection given: every src among the r_max best merges, and the rows
            # of the static layout left without a member are empty, their mean 0)
            want = members.mean(0) if len(members) else np.zeros(xs.shape[-1], np.float32)
            np.testing.assert_allclose(m[bi, g], want, rtol=1e-5, atol=1e-6)
    y = merge_lib.unmerge(m, match.group)
    for bi in range(2):
        for n in range(N):
            np.testing.assert_array_equal(y[bi, n], m[bi, group[bi, n]])  # every token its group's row


def test_dynamic_kv_slots_hold_exactly_the_kept_unmerged_src():
    cc = make_compression("regime", 24)
    plan = layer_plan(cc, 0, Geometry(S, H, W, NS))  # tile (3, 2)
    part = partition(Geometry(S, H, W, NS), cc.dst_seed)
    metric, sal = _inputs(5)
    prot = _protected(sal, plan.protect_per_frame)
    match = merge_lib.compute_match(jnp.asarray(metric), jnp.asarray(prot[:, part.src_pos]), plan, 0)
    idx, ok = kv_lib.dynamic_slots(plan, cc, match, jnp.asarray(prot))
    assert idx.shape == ok.shape == (2, plan.n_dyn)
    from rvggt_jax.compression.partition import kv_static_keep
    keep = kv_static_keep(Geometry(S, H, W, NS), plan.tile, True, True)
    unm = np.asarray(match.unm_pos)
    sizes = np.asarray(match.sizes)[:, plan.n_dst:]
    assert (sizes == 0).any()  # rows emptied by merges beyond the static r: no slot of theirs
    for bi in range(2):
        want = {plan.n_dst + u for u in range(plan.n_unm) if keep[unm[bi, u]] and sizes[bi, u] > 0}
        got = set(np.asarray(idx[bi])[np.asarray(ok[bi])].tolist())
        assert got == want
        assert len(want) <= plan.n_dyn


def test_band_cache_reuse_and_recompute():
    from rvggt_jax.compression import global_block, init_state
    from rvggt_jax.config import VGGTConfig
    from tests.helpers.compression_reference import global_positions, random_block_params

    cfg = VGGTConfig(embed_dim=32, num_heads=2).with_compression("regime")
    p = random_block_params(jax.random.PRNGKey(0), 32, 2)
    metric, sal = _inputs(2)
    x = jnp.asarray(np.random.default_rng(9).standard_normal((2, N, 32)), jnp.float32)
    pos = global_positions(S, H, W)
    seen, checks = {}, []

    def run(x, sal):  # traced once (eval_shape): the cache is a trace-time structure
        state = init_state(cfg.compression, sal, Geometry(S, H, W, NS))
        for layer in range(24):
            before = dict(state.matches)
            x, state = global_block(p, x, pos, layer, cfg, state)
            plan = layer_plan(cfg.compression, layer, Geometry(S, H, W, NS))
            if plan.match == "reuse":
                checks.append(state.matches[plan.match_key] is before[plan.match_key])
            elif plan.match_key is not None:
                checks.append(plan.match_key not in before)
                seen[plan.match_key] = layer
            else:
                checks.append(state.matches.keys() == before.keys())  # no-cache layers store nothing
        checks.append(set(state.kv) == {("band0_rho0.9900", (3, 2)), ("band1_rho0.5000", (5, 3)),
                                        ("band2_rho0.9900", (5, 3))})
        return x

    jax.eval_shape(run, x, jnp.asarray(sal))
    assert len(checks) == 25 and all(checks)
    assert seen == {"band0_rho0.9900": 0, "band1_rho0.5000": 14, "band2_rho0.9900": 18}

    # without cache every merging layer computes
    no_cache = make_compression("no_cache", 24)
    assert all(layer_plan(no_cache, i, Geometry(S, H, W, NS)).match == "compute" for i in range(24))


@pytest.mark.parametrize("na, nb, lead, width", [(37, 3536, (), 16), (20, 50, (3,), 10), (9, 16, (), 16),
                                                 (11, 7, (2,), None), (5, 33, (), 11), (6, 97, (), None)])
def test_best_is_the_first_index_reaching_each_rows_max(na, nb, lead, width):
    """`matching._best` (two levels: chunk maxima, then the first chunk and column reaching
    the row's max; one level when no chunk width from 8 to 32 divides the dst count)
    against numpy's argmax, the first index of the max: ties across and within chunks,
    -0.0 against 0.0, negative rows, a NaN row (its last index) and leading dims; the max
    is the row's."""
    assert matching._chunk_width(nb) == width
    rng = np.random.default_rng(nb)
    # a few distinct directions: many exact ties between the cosines
    dirs = rng.standard_normal((4, 6)).astype(np.float32)
    a = dirs[rng.integers(0, 4, lead + (na,))]
    d = dirs[rng.integers(0, 4, lead + (nb,))]
    a[..., 1, :] = 0.0  # every cosine 0.0: the first column
    a[..., 2, :] = -dirs[0]  # ties at a negative max unless some dst is opposite to dirs[0]
    if na > 4:
        a[..., 4, :] = np.nan
    a, d = matching.normalize(jnp.asarray(a)), matching.normalize(jnp.asarray(d))
    top, arg = jax.jit(matching._best, static_argnums=2)(a, d, nb)
    sims = np.asarray(jnp.einsum("...ic,...jc->...ij", a, d, precision="highest"))
    nan_row = np.isnan(sims).any(-1)
    want = np.where(nan_row, nb - 1, np.argmax(np.where(np.isnan(sims), -np.inf, sims), -1))
    np.testing.assert_array_equal(np.asarray(arg), want)
    np.testing.assert_array_equal(np.asarray(top)[~nan_row], sims.max(-1)[~nan_row])
    assert not np.isfinite(np.asarray(top)[nan_row]).any()  # (NaN, or -inf: XLA:CPU's max of NaN varies)


@pytest.mark.parametrize("shape, r", [((2, 100), 37), ((1, 3, 50), 20), ((1, 5000), 4000), ((2, 40), 0),
                                      ((2, 40), 40), ((1, 7), 1), ((1, 7), 6)])
def test_select_best_takes_the_set_a_stable_descending_sort_puts_first(shape, r):
    """`merge.select_best` (no sort: the r-th score found bit by bit) selects the first r
    of a stable argsort of -score (ties, the protected score, -0.0 against 0.0, negative
    scores and NaN included); the rest come ranked and listed in index order."""
    rng = np.random.default_rng(r)
    s = (rng.integers(-7, 7, shape) / 7).astype(np.float32)  # many ties, both signs
    s.reshape(-1)[:3] = merge_lib.PROTECTED_SCORE
    s.reshape(-1)[[4, 5, 6]] = np.nan, -0.0, 0.0
    merged, rank, rest = jax.jit(merge_lib.select_best, static_argnums=1)(jnp.asarray(s), r)
    order = np.asarray(jnp.argsort(-jnp.asarray(s), axis=-1, stable=True))
    want = np.zeros(shape, bool)
    np.put_along_axis(want, order[..., :r], True, axis=-1)
    np.testing.assert_array_equal(np.asarray(merged), want)
    for row in np.ndindex(shape[:-1]):
        unsel = np.flatnonzero(~want[row])
        np.testing.assert_array_equal(np.asarray(rest)[row], unsel)
        np.testing.assert_array_equal(np.asarray(rank)[row][unsel], np.arange(unsel.size))
