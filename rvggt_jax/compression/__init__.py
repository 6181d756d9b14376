"""RegimeVGGT compression of the global blocks (token merging + K/V downsampling).

    geometry = compression.Geometry(frames, h, w, num_special)
    state = compression.init_state(config.compression, saliency, geometry)
    x, state = compression.global_block(p_block, x, pos, layer, config, state)

The static half (the configuration and its presets, the partition of tokens, each layer's
plan) imports no model code, so `rvggt_jax.config` can hold a `CompressionConfig`; the
blocks themselves build on the model's block (`model.layers`). See docs/method.md.
"""

import importlib

# Public names resolved on first use: importing the configuration (compression.config,
# as rvggt_jax.config does) does not load the blocks, which import the model's layers.
_LAZY = {
    "global_block": "block",
    "State": "state", "init_state": "state",
    "PRESETS": "config", "CompressionConfig": "config", "LayerKind": "config", "make_compression": "config",
    "sigma_to_tile": "config",
    "Match": "merge",
    "Geometry": "partition",
    "LayerPlan": "plan", "layer_plan": "plan",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"rvggt_jax.compression.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'rvggt_jax.compression' has no attribute {name!r}")
