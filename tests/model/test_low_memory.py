"""The low-memory inference mode (`VGGTConfig.with_low_memory`, `rvggt plan --low-memory`):
the dense outputs in 16 bits, the camera head's weights stored like the aggregator's, and the
layers read at the DPT heads' coarse levels kept as their reassembled maps.

On the tiny checkpoint (token width 64, DPT out_channels 8/16/32/32, 16 features): layer 17
is then 16 + 16 channels on the patch grid instead of 64, layer 23 16 + 16 on a quarter of
it, with its camera token beside it.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.helpers import rel_err
from tests.helpers.tolerances import UPSTREAM_BF16
from rvggt_jax import rvggt_forward
from rvggt_jax.model.aggregator import aggregator_forward
from rvggt_jax.model.forward import _head_projections
from rvggt_jax.model.heads.dpt import HALF_OUTPUTS
from rvggt_jax.model.kept import KeptLayer, Part, ProjectedLayer
from rvggt_jax.weights.checkpoint import cast_params

HEADS = ("depth", "depth_conf", "world_points", "world_points_conf")
BOTH = {"depth_head": True, "point_head": True}
# one rounding to the output's 16-bit type, relative to the largest value (float16: 11
# significant bits, bfloat16: 8), on top of float32's 1e-4
ROUNDING = {"depth": 2.0 ** -11, "world_points": 2.0 ** -11, "depth_conf": 2.0 ** -8, "world_points_conf": 2.0 ** -8}


def test_low_memory_keeps_coarse_levels_reassembled(tiny, golden):
    params, config = tiny
    images = golden["images"]
    low = config.with_low_memory()
    grid = low.token_grid(images.shape[-2:])
    h, w = grid.hw
    proj = _head_projections(params, low, grid, False, BOTH)
    assert sorted(proj) == [4, 11, 17, 23]
    # the fine levels are upsampled by the heads (larger reassembled): projected as before
    assert proj[4].columns == (("depth_head", Part(0, 8)), ("point_head", Part(8, 8)))
    assert proj[17].columns == (("depth_head", Part(0, 16, (h, w))), ("point_head", Part(16, 16, (h, w))))
    quarter = (-(-h // 2), -(-w // 2))  # level 3's 3x3 conv of stride 2
    assert proj[23].columns == (("depth_head", Part(0, 16, quarter)), ("point_head", Part(16, 16, quarter)))
    assert proj[23].tokens == (0,) and proj[17].tokens == ()
    # the aggregator then keeps no layer as tokens: every kept value is a head's
    outs = jax.eval_shape(lambda p, x: aggregator_forward(p, x, low, set(), project=proj)[0],
                          params["aggregator"], images)
    s = images.shape[1]
    assert not any(isinstance(t, KeptLayer) for t in outs.values())
    assert all(isinstance(t, ProjectedLayer) and t.raw is None for t in outs.values())
    assert outs[23].buf.shape == (s, quarter[0] * quarter[1], 32) and outs[17].buf.shape == (s, h * w, 32)
    assert outs[23].token(0).shape == (1, s, 64)
    # the default mode reads 17 and 23 whole (the camera head reads 23's tokens)
    assert sorted(_head_projections(params, config, grid, False, BOTH)) == [4, 11]


def test_low_memory_float32_equals_the_fixture_up_to_16_bit_outputs(tiny, golden):
    params, config = tiny
    low = config.with_low_memory()
    fn = jax.jit(rvggt_forward, static_argnums=2)
    out = fn(params, golden["images"], low)
    for key, dt in zip(HEADS, HALF_OUTPUTS * 2):
        assert out[key].dtype == dt, key
        assert rel_err(np.asarray(out[key].astype(jnp.float32)), golden[key]) <= 1e-4 + ROUNDING[key], key
    assert out["pose_enc"].dtype == jnp.float32 and rel_err(out["pose_enc"], golden["pose_enc"]) <= 1e-4
    # the mode costs less memory: XLA's plan of the same program (outputs and temporaries)
    plans = {}
    for name, cfg in (("default", config), ("low", low)):
        m = fn.lower(params, golden["images"], cfg).compile().memory_analysis()
        plans[name] = m.output_size_in_bytes + m.temp_size_in_bytes
    assert plans["low"] < plans["default"], plans


def test_low_memory_bf16_within_twice_upstreams_own_deviation(tiny, golden):
    params, config = tiny
    low = config.with_dtype("bfloat16").with_low_memory()
    weights = cast_params(params, "bfloat16", heads=low.half_weight_heads)
    assert all(leaf.dtype == jnp.bfloat16 for leaf in jax.tree.leaves(weights["camera_head"]))
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(weights["depth_head"]))
    out = jax.jit(rvggt_forward, static_argnums=2)(weights, golden["images"], low)
    for key in ("pose_enc",) + HEADS:
        err = rel_err(np.asarray(out[key].astype(jnp.float32)), golden[key])
        assert err <= 2 * UPSTREAM_BF16[key], (key, err)


def test_low_memory_is_an_inference_mode(tiny):
    _, config = tiny
    with pytest.raises(ValueError, match="inference mode"):
        config.with_remat("full").with_low_memory()
    assert not config.low_memory and config.with_low_memory().with_low_memory(False) == config
