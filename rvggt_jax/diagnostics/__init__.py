"""The paper's diagnostics as a tool: the attention rank per layer, the saliency and
coverage maps, and a band schedule fitted to a model and its data.

    from rvggt_jax import diagnostics
    prof = diagnostics.rank_profile(params, images, config, m=256)   # r95/m per layer, head
    diagnostics.r95(rows)                       # one concrete [m, N] -> int
    comp, info = diagnostics.propose(prof["profile"])                # the fitted U-shape
    diagnostics.save_preset(comp, "mine.json"); diagnostics.load_preset("mine.json")

Modules: `rank` (attention rows of m sampled queries, singular values, r95, the
profile), `maps` (Psi, protected patches, kept K/V and their union coverage, merged
groups; PNGs), `calibrate` (the rule from r95/m to bands, merge ratios and K/V rates),
`presets_io` (preset files). `rvggt analyze` and `rvggt calibrate` drive them
(`rvggt_jax.app.diagnostics_command`); docs/diagnostics.md says how to read the plots.
"""

from rvggt_jax.diagnostics.calibrate import RULE, find_bands, kv_tile_for, merge_ratio_for, predicted_speedups, propose
from rvggt_jax.diagnostics.maps import (
    kv_keep_maps,
    kv_tiles,
    merge_bands,
    merged_groups,
    protected_patches,
    saliency_maps,
    union_coverage,
)
from rvggt_jax.diagnostics.presets_io import PresetError, is_preset_path, load_preset, resolve_preset, save_preset
from rvggt_jax.diagnostics.rank import (
    attention_rows,
    average_profiles,
    head_ranks,
    layer_head_ranks,
    layer_inputs,
    r95,
    r95_of_spectrum,
    rank_profile,
    sample_queries,
    singular_values,
)

__all__ = [
    "RULE", "PresetError", "attention_rows", "average_profiles", "find_bands", "head_ranks", "is_preset_path",
    "kv_keep_maps", "kv_tile_for", "kv_tiles", "layer_head_ranks", "layer_inputs", "load_preset", "merge_bands",
    "merge_ratio_for", "merged_groups", "predicted_speedups", "propose", "protected_patches", "r95",
    "r95_of_spectrum", "rank_profile", "resolve_preset", "sample_queries", "save_preset", "saliency_maps",
    "singular_values", "union_coverage",
]
