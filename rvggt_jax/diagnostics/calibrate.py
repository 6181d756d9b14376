"""A band schedule fitted to a rank profile: the rule of `rvggt calibrate`.

The paper reads its schedule off the normalised rank r95/m per layer (appendix
"Rank Spectrum of Global Attention"; Figure 1: shallow and deep effective rank <= 20,
the middle band peaking near 90, of m = 256 sampled rows): low flanks, a middle band
above the 0.30 "go-criterion"; merging is aggressive on the flanks and conservative on
the peak (rho 0.99 / 0.50 / 0.99), and the K/V keeper density is inverted (sigma
1.5 / 1.3 / 1.7: the densest K/V in the middle, the sparsest in the near-rank-1 deep
band). The stated rule below turns any profile into that U-shape, and gives back the
paper's values at the paper's measurements (20/256, 90/256, 1/256).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from rvggt_jax.compression.config import CompressionConfig, make_compression

FLAT = 20 / 256  # r95/m of the paper's flanks (rank <= 20 of 256): at or below it, the most merging
PEAK = 90 / 256  # r95/m of the paper's middle band (rank ~ 90 of 256)
GO = 0.30  # the paper's go-criterion for the middle band (drawn on the profile plot)
RHO_MAX = 0.99  # merge ratio at r95/m <= FLAT (the paper's flanks)
RHO_PEAK = 0.50  # merge ratio at r95/m = PEAK (the paper's middle band)
KEEP_FLOOR = 9 / 25  # K/V kept fraction at r95/m = 0 (sigma 1.7: the paper's near-rank-1 deep band)
KEEP_PEAK = 9 / 16  # K/V kept fraction at r95/m = PEAK (sigma 1.3: the paper's middle band)
# K/V tiles (t, k) a band may take, kept fraction (k/t)^2: sigma 1.7, 1.5, 1.3, none
TILES = ((5, 3), (3, 2), (4, 3), (1, 1))

RULE = f"""\
Bands (half maximum): tau = min + (max - min) / 2 of the mean profile r95/m; the middle
band is the run of consecutive layers with r95/m >= tau around the (first) maximum;
the layers before it are the shallow band, those after it the deep band (a flat
profile: one middle band over every layer).
Merge ratio of a band from its mean r95/m p: rho = {RHO_MAX} for p <= {FLAT:.4f} (20/256), then
linear through ({PEAK:.4f} (90/256), {RHO_PEAK}) and on down to 0 (clipped to [0, {RHO_MAX}], 2 decimals).
K/V rate of a band: target kept fraction {KEEP_FLOOR:.4f} + ({KEEP_PEAK:.4f} - {KEEP_FLOOR:.4f}) * p / {PEAK:.4f}
(capped at 1), rounded to the nearest tile (t, k) with kept (k/t)^2 among {list(TILES)}.
Cache: a match computed at the first layer of each band and reused in it, except the
first half (rounded up) of the middle band, which recomputes it every layer (the
paper's L11-L14 of L11-L18). K/V downsampling runs in every band (the paper's text);
everything else (protection by Psi, alpha, size bias, anchor, phase shift) as `regime`.
On the paper's profile (shallow 20/256, middle 90/256, deep 1/256) this gives back rho
0.99 / 0.50 / 0.99 and sigma 1.5 / 1.3 / 1.7."""


def find_bands(profile: Sequence[float]) -> tuple[int, int]:
    """(first middle layer, first deep layer), 0-based, of a rank profile [depth] r95/m,
    by the half-maximum rule (`RULE`)."""
    p = np.asarray(profile, np.float64)
    if p.ndim != 1 or p.size == 0:
        raise ValueError(f"a rank profile is one r95/m value per layer; got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("the rank profile holds NaN or infinite values")
    lo, hi = float(p.min()), float(p.max())
    if hi - lo <= 1e-9:
        return 0, p.size
    tau = lo + 0.5 * (hi - lo)
    peak = int(np.argmax(p))
    start = peak
    while start > 0 and p[start - 1] >= tau:
        start -= 1
    end = peak + 1
    while end < p.size and p[end] >= tau:
        end += 1
    return start, end


def merge_ratio_for(p: float) -> float:
    """Merge ratio rho of a band of mean r95/m `p` (`RULE`)."""
    if p <= FLAT:
        return RHO_MAX
    rho = RHO_MAX + (RHO_PEAK - RHO_MAX) * (p - FLAT) / (PEAK - FLAT)
    return round(min(RHO_MAX, max(0.0, rho)), 2)


def kv_tile_for(p: float) -> tuple[int, int]:
    """K/V tile (t, k) of a band of mean r95/m `p` (`RULE`)."""
    target = min(1.0, KEEP_FLOOR + (KEEP_PEAK - KEEP_FLOOR) * max(0.0, p) / PEAK)
    return min(TILES, key=lambda tk: (abs((tk[1] / tk[0]) ** 2 - target), tk[0]))


def propose(profile: Sequence[float], name: str = "calibrated", base: str = "regime"
            ) -> tuple[CompressionConfig, dict[str, Any]]:
    """The preset `RULE` derives from a rank profile [depth] r95/m (mean over heads and
    scenes): (its `CompressionConfig` named `name`, the fields of `base` otherwise; a
    dict of the bands, per-band mean r95/m, merge ratios and K/V tiles)."""
    if name == "dense":
        raise ValueError("a calibrated preset cannot be named 'dense' (that name means no compression)")
    p = np.asarray(profile, np.float64)
    depth = p.size
    mid, deep = find_bands(p)
    spans = ((0, mid), (mid, deep), (deep, depth))
    means = [float(p[a:b].mean()) if b > a else float(p.min()) for a, b in spans]
    rho = tuple(merge_ratio_for(m) for m in means)
    tiles = tuple(kv_tile_for(m) for m in means)
    recompute = tuple(range(mid, mid + math.ceil((deep - mid) / 2)))
    starts = tuple(sorted({s for s in (0, mid, deep) if s < depth}))
    comp = make_compression(
        base, depth, merge_ratio=rho, merge_bands=(mid, deep), kv_sigma=tiles, kv_bands=(mid, deep),
        merge_only_layers=(), cache_band_starts=starts, no_cache_layers=recompute)
    comp = dataclasses.replace(comp, name=name)
    names = ("shallow", "middle", "deep")
    info = dict(
        rule=RULE, bands={n: [a, b] for n, (a, b) in zip(names, spans)},
        band_rank={n: m for n, m in zip(names, means)},
        merge_ratio={n: r for n, r in zip(names, rho)},
        kv_tile={n: list(t) for n, t in zip(names, tiles)},
        kv_kept_fraction={n: (t[1] / t[0]) ** 2 for n, t in zip(names, tiles)},
        recompute_layers=list(recompute))
    return comp, info


def predicted_speedups(model_config, comp: CompressionConfig, frames: int, height: int, width: int,
                       against: str = "regime") -> dict[str, float]:
    """The cost model's predicted aggregator speedups over dense of `comp` and of the
    built-in `against` preset at (frames, height, width), and their ratio (> 1: `comp`
    is predicted faster than `against`)."""
    from rvggt_jax.planning.cost import cost_report

    ours = cost_report(dataclasses.replace(model_config, compression=comp), frames, height, width)["predicted_speedup"]
    ref = cost_report(model_config.with_compression(against), frames, height, width)["predicted_speedup"]
    return dict(frames=frames, height=height, width=width, speedup=ours, **{f"{against}_speedup": ref},
                ratio=ours / ref)
