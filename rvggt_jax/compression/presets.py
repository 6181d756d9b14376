"""Named compression presets: field overrides of `CompressionConfig`, written for the
24 global layers of VGGT (0-based layer indices). `make_compression` rescales the layer
indices for another depth.

`regime` is the authors' canonical configuration (`HYBRID_CONFIG` of
`eval/eval_scannet50.py` in Brandon-Z-226/RegimeVGGT) as their code executes it:

  layers  rho   K/V tile             match cache
  0-9     0.99  sigma 1.5 -> (3, 2)  computed at 0, reused to 9
  10-13   0.50  none (merge only)    recomputed every layer
  14-17   0.50  sigma 1.7 -> (5, 3)  computed at 14, reused to 17
  18-23   0.99  sigma 1.7 -> (5, 3)  computed at 18, reused to 23

Their sigma bands come from `middle_range=(10, 14)`: layers >= 14 take `sigma_deep`
(1.7), so the middle sigma 1.3 never runs (layers 10-13 are merge-only). METHOD_SPEC's
table lists 1.3 for 14-17; `kv_sigma=(1.5, 1.3, 1.7), kv_bands=(10, 18),
merge_only_layers=(10, 11, 12, 13)` gives that reading. See docs/method.md.

The ablations (`merge_only` ... `no_phase_shift`) each remove one component from
`regime`; the paper's ablation rows (merging alone / K/V alone with sigma 1.5
everywhere) are overrides of these, see docs/method.md.
"""

from __future__ import annotations

from typing import Any

_MIDDLE_RECOMPUTE = (10, 11, 12, 13)

REGIME: dict[str, Any] = dict(
    merge_ratio=(0.99, 0.50, 0.99),
    merge_bands=(10, 18),
    match_scope="sequence",
    match_metric="auto",
    cache_band_starts=(0, 10, 18),
    no_cache_layers=_MIDDLE_RECOMPUTE,
    protect="saliency",
    alpha=0.1,
    size_bias=True,
    kv_sigma=(1.5, 1.3, 1.7),
    kv_bands=(10, 14),
    merge_only_layers=_MIDDLE_RECOMPUTE,
    anchor=True,
    phase_shift=True,
    kv_protect_saliency=False,
)

PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "dense": {},
    "regime": REGIME,
    # The paper's text: sigma 1.3 in the whole middle band L11-L18 (K/V downsampling also
    # in L11-L14) and the Psi-protected patches always kept in K/V.
    "regime_paper": {**REGIME, "kv_bands": (10, 18), "merge_only_layers": (), "kv_protect_saliency": True},
    # Per-frame matching: src only match dst of their own frame, r per frame.
    "regime_local": {**REGIME, "match_scope": "frame"},
    # FastVGGT: merging in every global layer, r = 0.9 N (capped), every tenth token of
    # the sequence protected, no size bias, no cache, no K/V downsampling.
    "fastvggt": dict(
        merge_ratio=(0.9, 0.9, 0.9),
        match_metric="norm1",
        protect="stride",
        alpha=0.1,
        size_bias=False,
        cache_band_starts=(),
        kv_sigma=(1.0, 1.0, 1.0),
    ),
    # AVGGT-style: layers 0-8 attend within each frame, then the same 2x2 grid K/V
    # subsample (1/4 of the patches) in every frame, no anchor, no merging.
    "avggt": dict(
        merge_ratio=(0.0, 0.0, 0.0),
        frame_layers=tuple(range(9)),
        kv_sigma=(2, 2, 2),
        anchor=False,
        phase_shift=False,
        size_bias=False,
    ),
    # Ablations of `regime`, one component removed each.
    "merge_only": {**REGIME, "kv_sigma": (1.0, 1.0, 1.0)},
    "kv_only": {**REGIME, "merge_ratio": (0.0, 0.0, 0.0)},
    "no_cache": {**REGIME, "cache_band_starts": ()},
    "no_size_bias": {**REGIME, "size_bias": False},
    "no_anchor": {**REGIME, "anchor": False},
    "no_phase_shift": {**REGIME, "phase_shift": False},
}
