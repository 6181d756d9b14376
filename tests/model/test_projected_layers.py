"""Kept layers held as the DPT heads' first step (`kept.ProjectedLayer`,
`dpt.head_projections`): which layers are projected, what the aggregator then keeps, and
that the heads' values are those of the heads reading the tokens themselves.

VGGT-1B's depth and point heads project layer 4 to 256 + 256 and layer 11 to 512 + 512 of
its 2048 channels; the tiny checkpoint has the same ratios (8 + 8 and 16 + 16 of 64).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.helpers import rel_err
from rvggt_jax.model.aggregator import aggregator_forward
from rvggt_jax.model.forward import _head_projections
from rvggt_jax.model.heads import dpt
from rvggt_jax.model.heads.projections import head_projections
from rvggt_jax.model.kept import Part, ProjectedLayer

TOL = 1e-5
BOTH = {"depth_head": True, "point_head": True}


def _projections(params, config, images, with_track=False):
    grid = config.token_grid(images.shape[-2:])
    return _head_projections(params, config, grid, with_track, BOTH)


def test_layers_narrower_as_projections_are_projected(tiny, golden):
    params, config = tiny
    proj = _projections(params, config, golden["images"])
    # layers 17 and 23 are read at 32 + 32 = 64 channels, their full width (23 is the camera's too)
    assert {k: v.columns for k, v in proj.items()} == {
        4: (("depth_head", Part(0, 8)), ("point_head", Part(8, 8))),
        11: (("depth_head", Part(0, 16)), ("point_head", Part(16, 16)))}
    # the track head's extractor reads the same layers: its columns follow
    with_track = _projections(params, config, golden["images"], with_track=True)
    assert with_track[4].columns[-1] == ("track_head", Part(16, 8)) and with_track[11].width == 48
    # a training step with remat keeps the layers (`forward._head_projections`)
    grid = config.token_grid(golden["images"].shape[-2:])
    assert _head_projections(params, config.with_remat("full"), grid, False, BOTH) == {}
    # one head alone is narrower on every layer (32 of 64 on 17 and 23), but a layer read
    # raw (here 4; in the model the camera head's) is never projected
    alone = head_projections({"depth_head": (params["depth_head"], (4, 11, 17, 23), True)},
                                 config.token_grid(golden["images"].shape[-2:]), 64, raw={4})
    assert sorted(alone) == [11, 17, 23]


def test_aggregator_keeps_projections_in_place_of_the_layers(tiny, golden):
    """The kept buffers hold only the layers read raw: the frame halves of 17 and 23 (23's
    global half is the stream) and the global half of 17, where 4 slots and 3 were kept."""
    params, config = tiny
    images = golden["images"]
    proj = _projections(params, config, images)
    keep = set(config.needed_layers(False)) - set(proj)
    outs = jax.eval_shape(lambda p, x: aggregator_forward(p, x, config, keep, project=proj)[0],
                          params["aggregator"], images)
    assert isinstance(outs[4], ProjectedLayer) and outs[4].raw is None
    _, s, _, h, w = images.shape
    q = (h // 14) * (w // 14)
    assert outs[4].buf.shape == (s, q, 16) and outs[11].buf.shape == (s, q, 32)
    assert outs[17].frame_buf.shape[0] == 2 and outs[17].global_buf.shape[0] == 1


def test_heads_on_projections_equal_heads_on_the_tokens(tiny, golden):
    params, config = tiny
    images = golden["images"]
    grid = config.token_grid(images.shape[-2:])
    proj = _projections(params, config, images)
    keep = set(config.needed_layers(False))

    @jax.jit
    def run(p, x):
        agg, _, _ = aggregator_forward(p["aggregator"], x, config, keep, project=proj)
        raw = {i: (t.raw if isinstance(t, ProjectedLayer) else t) for i, t in agg.items()}
        heads = {k: p[k] for k in BOTH}
        return (dpt.dense_heads(heads, agg, config.dpt_head, grid), dpt.dense_heads(heads, raw, config.dpt_head, grid),
                agg[4].array())

    projected, tokens, layer4 = run(params, images)
    assert rel_err(layer4, golden["aggregated_04"]) <= TOL  # also kept whole: it was asked for
    for key in ("depth", "depth_conf", "world_points", "world_points_conf"):
        assert rel_err(projected[key], tokens[key]) <= TOL, key
        assert rel_err(projected[key], golden[key]) <= 1e-4, key


def test_heads_do_not_depend_on_the_layers_returned(tiny, golden):
    """In bfloat16 the projections are stored rounded: a returned layer is projected all
    the same, so the heads' values are the same whichever layers a caller asks for."""
    params, config = tiny
    from rvggt_jax import rvggt_forward
    from rvggt_jax.weights.checkpoint import cast_params

    bf16 = config.with_dtype("bfloat16")
    cast = cast_params(params, "bfloat16")
    plain = jax.jit(rvggt_forward)(cast, golden["images"], bf16)
    more = jax.jit(rvggt_forward)(cast, golden["images"], bf16.with_outputs(layers=(4, 11)))
    for key in ("depth", "world_points"):
        np.testing.assert_array_equal(np.asarray(plain[key]), np.asarray(more[key]))
    assert rel_err(more["aggregated_11"], golden["aggregated_11"]) <= 2e-2


def test_a_projected_layer_names_what_is_missing(tiny, golden):
    params, config = tiny
    images = golden["images"]
    proj = _projections(params, config, images)
    outs = jax.eval_shape(lambda p, x: aggregator_forward(p, x, config, {17, 23}, project=proj)[0],
                          params["aggregator"], images)
    with pytest.raises(ValueError, match="with_outputs"):
        outs[4].array()
    with pytest.raises(KeyError, match="track_head"):
        outs[4].part("track_head")
    with pytest.raises(ValueError, match="reader="):
        dpt.dpt_head(params["depth_head"], outs, config.dpt_head, config.token_grid(images.shape[-2:]))
    with pytest.raises(ValueError, match="unknown DPT reader"):
        head_projections({"camera_head": (params["depth_head"], (4, 11, 17, 23), True)},
                             config.token_grid(images.shape[-2:]), 64)
    assert jnp.dtype(outs[4].buf.dtype) == jnp.float32
