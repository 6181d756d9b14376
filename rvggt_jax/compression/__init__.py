"""RegimeVGGT compression of the global blocks (token merging + K/V downsampling).

    state = compression.init_state(config, saliency, frames, (h, w))
    x, state = compression.global_block(p_block, x, pos, layer, config, state)

See docs/method.md.
"""

from rvggt_jax.compression.block import (Geometry, dense_global_block, empty_match, global_block, init_state,
                                         record_shapes)
from rvggt_jax.compression.config import PRESETS, CompressionConfig, make_compression, sigma_to_tile
from rvggt_jax.compression.plan import LayerPlan, layer_plan

__all__ = [
    "CompressionConfig", "Geometry", "dense_global_block", "empty_match", "LayerPlan", "PRESETS", "global_block", "init_state", "layer_plan",
    "make_compression", "record_shapes", "sigma_to_tile",
]
