"""The static shape plan of one global layer: every size the compressed block uses,
derived from (configuration, layer, frames, grid) alone. The block and the cost model
(`rvggt_jax.planning.cost`) both read it, so they cannot disagree.

Query layout of a merging layer: [dst (N_dst, static order) ; unmerged src (U,
data-dependent)], N_m = N_dst + U = N - r; under saliency protection up to r_max - r of
the U rows are empty (their src merged after all: the authors' count, `r_max`). K/V
slots: the dst kept for static reasons (`kv_fixed`, static indices), then `n_dyn` slots
compacted from the data-dependent candidates (unmerged src on the sub-grid;
Psi-protected tokens in the paper variant; filled ones first: on one device a layer
attends with the first `n_dyn_cap`, `kv_capacity` times the expected count, unless this
data fills more), then `n_dup` slots for duplicates of the protected dst tokens
(authors' artefact, off by default; a slot whose protected token is a src stays empty);
with them, `n_dup` query
rows after the N_m merged ones (the protected tokens' own queries, dst first: `n_dup`
covers the protected dst, exactly under stride protection, `duplicate_capacity` times
their expected count under saliency protection, where a sequence with more takes all
`n_dup_all`). When every unprotected src merges (the authors' count reaching all src, U
equal to the protected count), the U rows are the protected tokens' own rows instead
(`protected_rows`): a protected src's row is its own already, and a protected dst's own
row fills one of the rows its group's extra merges emptied, so the duplicates need no
rows or slots of their own.
Slots left empty are masked through the size column (g = 0 -> a large negative finite
logit).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from rvggt_jax.compression.config import CompressionConfig, LayerKind
from rvggt_jax.compression.partition import (
    Geometry,
    Partition,
    _ro,
    kv_static_keep,
    partition,
    saliency_protect_count,
    stride_protected,
)


@dataclass(frozen=True)
class LayerPlan:
    layer: int
    kind: LayerKind  # DENSE | FRAME | MERGE (r > 0) | KV (no merging, K/V subsampled)
    geometry: Geometry
    frames: int
    tokens: int  # N = S * L
    per_frame: int  # L
    r: int  # merged src tokens (0 unless kind is MERGE)
    n_dst: int
    n_src: int
    n_unm: int  # U: src tokens left unmerged
    n_query: int  # N_m
    tile: tuple[int, int]
    kv_mode: str  # "all" (every query token is a key) | "select"
    n_fixed: int  # static K/V slots (always filled)
    n_dyn: int  # data-dependent K/V slots (bound)
    n_dup: int  # query rows and K/V slots for the protected dst's own copies (a bound: the protected
    # tokens come dst first, `State.protected_pos`; a slot beyond the protected dst stays empty)
    n_kv: int  # K/V slots in total
    expected_dyn: float  # expected filled dynamic slots (src survival independent of position)
    expected_dup: float  # expected filled duplicate slots
    masked: bool  # some K/V slot may be empty
    size_column: bool  # the attention gets the extra Q/K column
    match: str  # "none" | "compute" | "reuse"
    match_key: str | None
    metric: str
    scope: str
    r_frame: int  # r per frame (frame scope)
    match_pairs: int  # src x dst similarity pairs evaluated when match == "compute"
    protect_per_frame: int  # protected patches per frame >= 1 (saliency protection)
    # The most src a merging layer merges: min(int(rho N), N_src). Under saliency protection
    # (sequence scope) the authors merge min(r_max, unprotected src), data-dependent and at
    # least r: the extra ones leave their rows of the static layout empty (`Match.sizes` 0).
    r_max: int = 0
    # The U unmerged rows are the protected tokens' own rows, in `State.protected_pos`
    # order (duplicate_protected, saliency protection, every unprotected src merging and
    # U equal to the protected count): n_dup is then 0. Same queries and keys as the
    # layout with n_dup extra rows, minus its copies of the protected src rows and its
    # empty rows.
    protected_rows: bool = False
    # Every protected token's own row (the duplicates' list, `protected_pos`); when more
    # than n_dup of them are dst (saliency protection; `duplicate_capacity`), the layer
    # attends with all n_dup_all. Rows of the output: N_m + n_dup_all.
    n_dup_all: int = 0
    # The dynamic K/V slots a merging layer attends with on one device (`kv_capacity` times
    # their expected count, at most n_dyn): the filled ones come first, and a sequence with
    # more than this many filled attends with all n_dyn (`lax.cond`, same values).
    # n_dyn for the other kinds (no capacity).
    n_dyn_cap: int = 0
    # The static index sets of a compressed layer (None for DENSE and FRAME), computed with
    # the plan so that the block reads them from it (not compared: they follow from the
    # fields above and the configuration).
    partition: Partition | None = field(default=None, compare=False, repr=False)
    kv_keep: np.ndarray | None = field(default=None, compare=False, repr=False)  # [N] `kv_static_keep`
    fixed_kv: np.ndarray | None = field(default=None, compare=False, repr=False)  # [n_fixed] into the queries
    # [n] indices into the src list of the src the layer matches, None: every src. Under
    # stride protection the protected src are static and never merge (r leaves them out):
    # no similarities are computed for them (FastVGGT's alpha 0.1: a tenth of the src)
    matched_src: np.ndarray | None = field(default=None, compare=False, repr=False)

    @property
    def n_kv_cap(self) -> int:
        """The K/V slots the layer attends with on one device unless a sequence fills more
        than `n_dyn_cap` dynamic slots (then `n_kv`)."""
        return self.n_kv - self.n_dyn + self.n_dyn_cap


def _merge_counts(comp: CompressionConfig, layer: int, geom: Geometry, part: Partition):
    """(r, r_frame) of a layer."""
    N = geom.tokens
    n_src = part.src_pos.size
    rho = comp.layer_merge_ratio(layer)
    protected_per_frame = saliency_protect_count(geom, comp.alpha) if comp.protect == "saliency" else 0
    if comp.match_scope == "sequence":
        if comp.protect == "stride":
            p_src = int((~part.is_dst[stride_protected(N, comp.alpha)]).sum())
        else:
            p_src = (geom.frames - 1) * protected_per_frame
        return max(0, min(int(N * rho), n_src - p_src)), 0
    n_src_f = part.src_pos_f.shape[1]
    if comp.protect == "stride" and geom.frames > 1:
        prot = np.zeros(N, bool)
        prot[stride_protected(N, comp.alpha)] = True
        protected_src_per_frame = int(prot[part.src_pos_f].sum(axis=1).max())
    else:
        protected_src_per_frame = protected_per_frame
    r_f = max(0, min(int(geom.per_frame * rho), n_src_f - protected_src_per_frame)) if geom.frames > 1 else 0
    return (geom.frames - 1) * r_f, r_f


def _protected_count(comp: CompressionConfig, geom: Geometry) -> int:
    """Upper bound on protected tokens (exact for stride protection)."""
    if comp.protect == "saliency":
        return (geom.frames - 1) * saliency_protect_count(geom, comp.alpha)
    if comp.protect == "stride":
        return int(stride_protected(geom.tokens, comp.alpha).size)
    return 0


def _expected_duplicates(comp: CompressionConfig, part: Partition, keep: np.ndarray | None, geom: Geometry) -> float:
    """Expected duplicated protected tokens: those that are dst (and kept as K/V when
    `keep` [N] masks the duplicates). Exact for stride protection; for saliency, the
    top patches of frames >= 1 are taken to fall anywhere in their frame."""
    ok = part.is_dst if keep is None else part.is_dst & keep
    if comp.protect == "stride":
        return float(ok[stride_protected(geom.tokens, comp.alpha)].sum())
    return _expected_protected_kept(ok, geom, _protected_count(comp, geom))


def _expected_protected_kept(keep: np.ndarray, geom: Geometry, count: int) -> float:
    """Expected saliency-protected tokens where `keep` [N] is True: the top patches of
    frames >= 1 (`count` of them) taken to fall anywhere in their frame."""
    pos = np.arange(geom.per_frame, geom.tokens)
    later_patches = pos[pos % geom.per_frame >= geom.num_special]  # where saliency protection can fall
    return count * float(keep[later_patches].mean()) if later_patches.size else 0.0


def _merged_kv_slots(part: Partition, keep: np.ndarray, U: int, geom: Geometry, p_max: int, protected_rows: bool,
                     kv_keeps_protected: bool) -> tuple[int, int, float]:
    """(n_fixed, n_dyn, expected filled dynamic slots) of a K/V-downsampled merging layer:
    the kept dst (static), and the bound on the unmerged src (or protected rows, or
    protected tokens) on the grid, with the count expected to be filled."""
    n_dst, n_src = part.dst_pos.size, part.src_pos.size
    n_fixed = int(keep[part.dst_pos].sum())
    e_src = int(keep[part.src_pos].sum())
    n_dyn = min(U, e_src)
    exp_dyn = U * e_src / max(n_src, 1)
    if protected_rows:  # the rows' tokens are dst or src: any of them may be on the grid
        n_dyn = U
        exp_dyn = _expected_protected_kept(keep, geom, p_max)
    if kv_keeps_protected:
        pool = U + (n_dst - n_fixed)
        n_dyn = min(pool, n_dyn + p_max)
        exp_dyn = min(float(n_dyn), exp_dyn + p_max * (1.0 - (n_fixed + e_src) / max(n_dst + n_src, 1)))
    return n_fixed, n_dyn, exp_dyn


@functools.lru_cache(maxsize=4096)
def layer_plan(comp: CompressionConfig, layer: int, geom: Geometry) -> LayerPlan:
    """The static plan of global layer `layer` over a sequence of shape `geom`."""
    L = geom.per_frame
    N = geom.tokens
    kind = comp.layer_kind(layer)
    tile = comp.layer_tile(layer)
    base = dict(layer=layer, geometry=geom, frames=geom.frames, tokens=N, per_frame=L, tile=tile,
                scope=comp.match_scope, metric=comp.layer_metric(layer), protect_per_frame=0)
    # what a layer without merging or K/V selection has (DENSE: every token; FRAME: per frame)
    uncompressed = dict(r=0, n_dst=N, n_src=0, n_unm=0, n_query=N, kv_mode="all", n_dyn=0, n_dup=0,
                        expected_dyn=0.0, expected_dup=0.0, masked=False, size_column=False, match="none",
                        match_key=None, r_frame=0, match_pairs=0)
    if kind in (LayerKind.DENSE, LayerKind.FRAME):
        keys = L if kind == LayerKind.FRAME else N
        return LayerPlan(kind=kind, n_fixed=keys, n_kv=keys, **uncompressed, **base)

    part = partition(geom, comp.dst_seed)
    n_dst, n_src = part.dst_pos.size, part.src_pos.size
    r, r_f = _merge_counts(comp, layer, geom, part)
    kv_keeps_protected = comp.kv_protect_saliency and comp.protect == "saliency" and tile != (1, 1)
    p_max = _protected_count(comp, geom)
    base["protect_per_frame"] = saliency_protect_count(geom, comp.alpha) if comp.protect == "saliency" else 0
    keep = kv_static_keep(geom, tile, comp.phase_shift, comp.anchor)
    index = dict(partition=part, kv_keep=keep)

    if r == 0:
        # No merging: queries are the tokens in their own order.
        if tile == (1, 1):
            return LayerPlan(kind=LayerKind.DENSE, n_fixed=N, n_kv=N, **uncompressed, **base)
        n_fixed = int(keep.sum())
        n_dyn = min(N - n_fixed, p_max) if kv_keeps_protected else 0
        # Expected protected non-kept patches: protection independent of the grid.
        exp_dyn = p_max * (1.0 - n_fixed / N) if kv_keeps_protected else 0.0
        return LayerPlan(kind=LayerKind.KV, r=0, n_dst=N, n_src=0, n_unm=0, n_query=N, kv_mode="select",
                         n_fixed=n_fixed, n_dyn=n_dyn, n_dyn_cap=n_dyn, n_dup=0, n_kv=n_fixed + n_dyn,
                         expected_dyn=exp_dyn,
                         expected_dup=0.0, masked=n_dyn > 0, size_column=n_dyn > 0, match="none",
                         match_key=None, r_frame=0, match_pairs=0, fixed_kv=_ro(np.flatnonzero(keep)),
                         **index, **base)

    U = n_src - r
    n_query = n_dst + U
    key = comp.cache_key(layer)
    match = "compute"
    if key is not None:
        for prev in range(layer):
            if (comp.layer_kind(prev) == LayerKind.COMPRESSED and comp.cache_key(prev) == key
                    and _merge_counts(comp, prev, geom, part)[0] > 0):
                match = "reuse"
                break
    matched_src = None
    if comp.match_scope == "sequence" and comp.protect == "stride":
        matched_src = _ro(np.flatnonzero(~np.isin(part.src_pos, stride_protected(N, comp.alpha))))
    if comp.match_scope == "sequence":
        pairs = (n_src if matched_src is None else matched_src.size) * n_dst
    else:
        pairs = (geom.frames - 1) * part.src_pos_f.shape[1] * part.dst_rank_f.shape[1]

    # a duplicate slot is empty when its protected token is a src (or off the K/V grid); an
    # unmerged row when its src merged beyond the static r
    r_max = r
    if comp.match_scope == "sequence" and comp.protect == "saliency":
        r_max = max(r, min(int(geom.tokens * comp.layer_merge_ratio(layer)), n_src))
    # every unprotected src merges and the U rows number the protected tokens: the rows
    # the extra merges empty are exactly as many as the protected dst (their own rows)
    protected_rows = (comp.duplicate_protected and r_max == n_src and U == p_max > 0
                      and comp.match_scope == "sequence" and comp.protect == "saliency"
                      and not kv_keeps_protected)
    n_dup_all = p_max if comp.duplicate_protected and not protected_rows else 0
    n_dup = n_dup_all
    if n_dup_all and comp.protect == "stride":  # the protected dst are known
        n_dup = int(part.is_dst[stride_protected(N, comp.alpha)].sum())
    elif n_dup_all:
        expected = _expected_duplicates(comp, part, None, geom)
        n_dup = min(n_dup_all, 8 * math.ceil(comp.duplicate_capacity * expected / 8))
    if tile == (1, 1):
        kv_mode, n_fixed, n_dyn, exp_dyn = "all", n_query, 0, 0.0
    else:
        kv_mode = "select"
        n_fixed, n_dyn, exp_dyn = _merged_kv_slots(part, keep, U, geom, p_max, protected_rows, kv_keeps_protected)
    dup_masked = tile != (1, 1) and not kv_keeps_protected
    # the slots this data fills are about exp_dyn: attend with a margin over that (the
    # filled slots come first; more filled than this takes the layer's second branch)
    n_dyn_cap = min(n_dyn, 8 * math.ceil(comp.kv_capacity * exp_dyn / 8))
    exp_dup = 0.0
    if n_dup:
        exp_dup = _expected_duplicates(comp, part, keep if dup_masked else None, geom)
    masked = n_dyn > 0 or n_dup > 0 or r_max > r
    return LayerPlan(kind=LayerKind.MERGE, r=r, n_dst=n_dst, n_src=n_src, n_unm=U, n_query=n_query,
                     kv_mode=kv_mode, n_fixed=n_fixed, n_dyn=n_dyn, n_dyn_cap=n_dyn_cap, n_dup=n_dup,
                     n_kv=n_fixed + n_dyn + n_dup,
                     expected_dyn=exp_dyn, expected_dup=exp_dup, masked=masked,
                     size_column=masked or comp.size_bias,
                     match=match, match_key=key, r_frame=r_f, match_pairs=pairs, r_max=r_max,
                     protected_rows=protected_rows, n_dup_all=n_dup_all, matched_src=matched_src,
                     fixed_kv=_ro(np.flatnonzero(keep[part.dst_pos])) if kv_mode == "select" else None,
                     **index, **base)


def padded_head_dim(d: int, size_column: bool, multiple: int) -> int:
    """Head dimension of the folded attention operands."""
    if not size_column:
        return d
    return int(math.ceil((d + 1) / multiple) * multiple)


def check_shapes(plan: LayerPlan, comp: CompressionConfig, queries: int, keys, log_g, dup: int | None = None,
                 dyn: int | None = None) -> None:
    """At trace time: the attention's queries, K/V slots (keys [B, M, H, D]) and folded head
    dimension (log_g: the size bias, or None) are the plan's (what the cost model reads);
    `dup`: the duplicate slots attended (default n_dup; n_dup_all in the overflow branch);
    `dyn`: the dynamic slots attended (default n_dyn; n_dyn_cap in the capacity branch)."""
    d = keys.shape[-1]
    n_kv = plan.n_fixed + (plan.n_dyn if dyn is None else dyn) + (plan.n_dup if dup is None else dup)
    want = (plan.n_query, n_kv, padded_head_dim(d, plan.size_column, comp.head_pad_multiple))
    got = (queries, keys.shape[1], padded_head_dim(d, log_g is not None, comp.head_pad_multiple))
    if got != want:
        raise AssertionError(f"global block {plan.layer}: (queries, K/V slots, head dim) {got} but the plan "
                             f"says {want}")
