"""RegimeVGGT compression of the global blocks (token merging + K/V downsampling).

    geometry = compression.Geometry(frames, h, w, num_special)
    state = compression.init_state(config.compression, saliency, geometry)
    x, state = compression.global_block(p_block, x, pos, layer, config, state)

See docs/method.md.
"""

from rvggt_jax.compression.block import global_block
from rvggt_jax.compression.state import State, init_state
from rvggt_jax.compression.config import PRESETS, CompressionConfig, LayerKind, make_compression, sigma_to_tile
from rvggt_jax.compression.merge import Match
from rvggt_jax.compression.partition import Geometry
from rvggt_jax.compression.plan import LayerPlan, layer_plan

__all__ = [
    "CompressionConfig", "Geometry", "LayerKind", "LayerPlan", "Match", "PRESETS", "State",
    "global_block", "init_state", "layer_plan", "make_compression", "sigma_to_tile",
]
