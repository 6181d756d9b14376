"""Flax modules and random init: the init tree is the converter's tree (paths, shapes,
dtypes) for the micro, the tiny-fixture, a different-hidden-size and the VGGT-1B
layouts; values follow upstream's initialisation; `VGGT.apply` equals `rvggt_forward`
bit for bit; an `Aggregator` inside a user's module takes converted weights."""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rvggt_jax
from rvggt_jax.weights.converter import expected_param_shapes
from rvggt_jax.config import DPTHeadConfig, TrackHeadConfig, VGGTConfig
from rvggt_jax.model.initializers import BLOCK, InitSpec, draw
from rvggt_jax.model.forward import rvggt_forward
from rvggt_jax.model.modules import VGGT, Aggregator
from tests.helpers import TINY
from tests.helpers.micro import micro_config

KEY = jax.random.PRNGKey(0)


def _spec(tree):
    return jax.tree.map(lambda x: (tuple(x.shape), jnp.dtype(x.dtype).name), tree)


def _hidden_layout() -> VGGTConfig:
    """Other widths everywhere: 48-wide tokens, MLP ratio 2, other DPT/track sizes."""
    return micro_config(embed_dim=48, num_heads=3, mlp_ratio=2.0, depth=3,
                        dpt_head=DPTHeadConfig(features=16, out_channels=(8, 12, 24, 24),
                                               intermediate_layer_idx=(0, 1, 1, 2)),
                        track_head=TrackHeadConfig(features=12, hidden_size=24, corr_levels=3, corr_radius=2))


@pytest.fixture(scope="module")
def micro():
    config = micro_config()
    return config, rvggt_jax.init_params(config, KEY)


@pytest.mark.parametrize("layout", ["tiny", "hidden", "vggt_1b"])
def test_init_tree_is_the_converter_tree(layout):
    """Abstract only (jax.eval_shape): nothing of the 1B layout is allocated."""
    if layout == "tiny":
        config = VGGTConfig.from_json(TINY / "config.json")
    else:
        config = _hidden_layout() if layout == "hidden" else VGGTConfig.vggt_1b()
    got = jax.eval_shape(rvggt_jax.init_params, config, KEY)
    assert _spec(got) == _spec(expected_param_shapes(config))
    if layout == "hidden":  # (tracing a whole forward of the 24-layer layouts costs ~10 s)
        # the module's own init (with images, no query points) registers the same tree
        images = jax.ShapeDtypeStruct((1, 2, 3, 28, 28), jnp.float32)
        via_init = jax.eval_shape(lambda k, x: VGGT(config).init(k, x)["params"], KEY, images)
        assert _spec(via_init) == _spec(got)


def test_init_without_track_head_follows_config(micro):
    config = dataclasses.replace(micro[0], enable_track=False)
    got = jax.eval_shape(rvggt_jax.init_params, config, KEY)
    assert "track_head" not in got
    assert _spec(got) == _spec(expected_param_shapes(config, skip_track=True))


def test_init_values_follow_upstream(micro):
    config, p = micro
    agg = p["aggregator"]
    assert np.all(np.asarray(agg["frame_blocks"]["0"]["ls1"]["gamma"]) == np.float32(0.01))
    assert np.all(np.asarray(agg["patch_embed"]["blocks"]["0"]["ls2"]["gamma"]) == 1.0)  # DINO init_values
    assert np.all(np.asarray(agg["frame_blocks"]["1"]["norm1"]["scale"]) == 1.0)
    assert np.all(np.asarray(agg["frame_blocks"]["1"]["norm1"]["bias"]) == 0.0)
    assert np.all(np.asarray(agg["patch_embed"]["mask_token"]) == 0.0)
    assert np.all(np.asarray(p["camera_head"]["empty_pose_tokens"]) == 0.0)
    assert 0 < np.abs(np.asarray(agg["camera_token"])).max() < 1e-5  # normal, std 1e-6
    # DINO linears: trunc_normal std 0.02 (tolerance: the std of 32*32 draws, ~3 sigma)
    q = np.asarray(agg["patch_embed"]["blocks"]["0"]["attn"]["q"]["kernel"])
    assert abs(q.std() - 0.02) < 0.02 * 3 / np.sqrt(2 * q.size)
    assert np.all(np.asarray(agg["patch_embed"]["blocks"]["0"]["attn"]["q"]["bias"]) == 0.0)
    # torch default Linear: U(+-1/sqrt(fan_in)), fan_in 32 (the fused qkv's input width)
    k = np.asarray(agg["global_blocks"]["2"]["attn"]["k"]["kernel"])
    bound = 1 / np.sqrt(config.embed_dim)
    assert np.abs(k).max() <= bound and np.abs(k).max() > 0.9 * bound
    fh = np.asarray(p["track_head"]["tracker"]["updateformer"]["flow_head"]["kernel"])
    assert 0 < fh.std() < 0.002  # trunc_normal std 0.001
    # different keys, different trees; the same key, the same tree
    other = rvggt_jax.init_params(config, 1)
    assert not np.array_equal(np.asarray(other["aggregator"]["camera_token"]), np.asarray(agg["camera_token"]))


def test_draw_in_blocks_has_the_distribution():
    """Leaves larger than one block: stitched blocks, no repeated block."""
    x = np.asarray(draw(InitSpec("uniform", 0.5), KEY, (3, BLOCK)))
    assert x.shape == (3, BLOCK) and np.abs(x).max() <= 0.5
    assert not np.array_equal(x[0], x[1])
    assert abs(x.std() - 0.5 / np.sqrt(3)) < 0.01  # U(-b, b) has std b/sqrt(3); 196k draws
    with pytest.raises(ValueError, match="unknown init kind"):
        draw(InitSpec("laplace", 1.0), KEY, (2,))


def test_init_params_rejects_bad_config():
    with pytest.raises(TypeError, match="VGGTConfig"):
        rvggt_jax.init_params({"embed_dim": 32}, 0)


def test_apply_equals_rvggt_forward_bit_for_bit(micro):
    config, params = micro
    images = jnp.asarray(np.random.default_rng(0).random((1, 2, 3, 28, 42)), jnp.float32)
    a = jax.jit(lambda p, x: VGGT(config).apply({"params": p}, x))(params, images)
    b = jax.jit(rvggt_forward)(params, images, config)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_missing_or_misshaped_weights_are_named(micro):
    config, params = micro
    images = jnp.zeros((1, 2, 3, 28, 28), jnp.float32)
    broken = jax.tree.map(lambda x: x, params)
    del broken["depth_head"]["norm"]
    with pytest.raises(Exception, match="norm"):
        jax.eval_shape(lambda p: VGGT(config).apply({"params": p}, images), broken)
    bad = jax.tree.map(lambda x: x, params)
    bad["aggregator"]["camera_token"] = jnp.zeros((1, 2, 1, 16))
    with pytest.raises(Exception, match="camera_token"):
        jax.eval_shape(lambda p: VGGT(config).apply({"params": p}, images), bad)


class _UserModel(nn.Module):
    """A user's model with the aggregator as its backbone."""

    config: VGGTConfig

    @nn.compact
    def __call__(self, images):
        tokens = Aggregator(self.config, name="backbone")(images, layers=(self.config.depth - 1,))
        return nn.Dense(1, name="readout")(tokens[self.config.depth - 1][:, :, 0])  # camera token [B, S, 2C]


def test_aggregator_as_backbone_takes_converted_weights(tiny):
    params, config = tiny  # the converted tiny checkpoint
    model = _UserModel(config)
    images = jnp.asarray(np.random.default_rng(1).random((1, 2, 3, 28, 28)), jnp.float32)
    shapes = jax.eval_shape(lambda k: model.init(k, images)["params"], KEY)
    assert _spec(shapes["backbone"]) == _spec(params["aggregator"])
    user = {"backbone": params["aggregator"],
            "readout": {"kernel": jnp.ones((2 * config.embed_dim, 1)), "bias": jnp.zeros((1,))}}
    got = jax.jit(lambda p, x: model.apply({"params": p}, x))(user, images)
    ref = jax.jit(rvggt_forward)(params, images, config.with_outputs(layers=(config.depth - 1,)))
    want = ref[f"aggregated_{config.depth - 1:02d}"][:, :, 0].sum(-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-5)  # a float32 sum over 64
    with pytest.raises(rvggt_jax.InputError, match="layer indices"):
        Aggregator(config).apply({"params": params["aggregator"]}, images, layers=(99,))
