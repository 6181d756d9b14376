"""DPT head parity with the upstream PyTorch outputs of the tiny fixture."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax import init_params
from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.heads import conv, dpt, resize
from tests.helpers import TINY, rel_err
from tests.helpers.heads_params import load_head_params, load_io

RTOL = 1e-4
TRANSPOSED = ("resize_layers.0", "resize_layers.1")


@pytest.fixture(scope="module")
def setup():
    config = VGGTConfig.from_json(TINY / "config.json")
    io = load_io()
    # A dict of only the layers the head reads, as the model keeps them.
    aggregated = {i: jnp.asarray(io[f"aggregated_{i:02d}"]) for i in config.dpt_head.intermediate_layer_idx}
    image_hw = io["images"].shape[-2:]
    return config, io, aggregated, image_hw


# Frames per group of the head: 3 at the default (one group), 1 (three groups), and 2
# (two groups, the second padded with a zero frame).
FRAME_GROUPS = {"all": None, "one": 1, "two": 2 * 112 * 154}


@pytest.mark.parametrize("groups", FRAME_GROUPS)
@pytest.mark.parametrize("name, head, pred_key", [
    ("depth_head", dpt.depth_head, "depth"),
    ("point_head", dpt.point_head, "world_points"),
])
def test_dense_head_matches_upstream(setup, name, head, pred_key, groups, monkeypatch):
    config, io, aggregated, image_hw = setup
    if FRAME_GROUPS[groups] is not None:
        monkeypatch.setattr(dpt, "GROUP_PIXELS", FRAME_GROUPS[groups])
    expected = {"all": 3, "one": 1, "two": 2}[groups]
    assert dpt.frames_per_group(3, image_hw) == expected
    params = load_head_params(name, TRANSPOSED)
    # a fresh function per case: jit's trace cache must not reuse another grouping
    pred, conf = jax.jit(lambda p, a: head(p, a, config.dpt_head, config.token_grid(image_hw)))(params, aggregated)
    e_pred = rel_err(pred, io[pred_key])
    e_conf = rel_err(conf, io[pred_key + "_conf"])
    print(f"{name}: rel err {pred_key} {e_pred:.3g}, {pred_key}_conf {e_conf:.3g}")
    assert e_pred <= RTOL and e_conf <= RTOL


def test_feature_only_shape_and_finite(setup):
    config, io, aggregated, image_hw = setup
    params = load_head_params("track_head.feature_extractor", TRANSPOSED)
    layer_idx = config.track_layer_idx
    tokens = {i: jnp.asarray(io[f"aggregated_{i:02d}"]) for i in layer_idx}
    feats = jax.jit(dpt.dpt_features, static_argnums=2, static_argnames="layer_idx")(
        params, tokens, config.token_grid(image_hw), layer_idx=layer_idx)
    b, s, _, h, w = io["images"].shape
    assert feats.shape == (b, s, h // 2, w // 2, config.track_head.features)
    assert np.all(np.isfinite(np.asarray(feats)))
    assert float(jnp.std(feats)) > 0


def test_align_corners_resize_matches_formula():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((2, 3, 5, 4)).astype(np.float32)
    y = np.asarray(dpt.resize_bilinear_align_corners(jnp.asarray(x), (7, 9)))
    # Corners coincide exactly; an interior sample is the bilinear mix at (i*(H-1)/(Ho-1), ...).
    np.testing.assert_array_equal(y[:, [0, -1]][:, :, [0, -1]], x[:, [0, -1]][:, :, [0, -1]])
    sy, sx = 3 * 2 / 6, 5 * 4 / 8  # output (3, 5) -> source (1.0, 2.5)
    ref = 0.5 * x[:, 1, 2] + 0.5 * x[:, 1, 3]
    assert sy == 1.0 and sx == 2.5
    np.testing.assert_allclose(y[:, 3, 5], ref, rtol=1e-6, atol=1e-6)


def test_conv_transpose_patchwise_matches_scatter():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((1, 2, 3, 4)).astype(np.float32)
    kernel = rng.standard_normal((2, 2, 4, 5)).astype(np.float32)
    bias = rng.standard_normal(5).astype(np.float32)
    y = np.asarray(dpt.conv_transpose_patchwise({"kernel": kernel, "bias": bias}, jnp.asarray(x)))
    ref = np.zeros((1, 4, 6, 5), np.float32) + bias
    for i in range(2):
        for j in range(3):
            for a in range(2):
                for c in range(2):
                    ref[0, 2 * i + a, 2 * j + c] += x[0, i, j] @ kernel[a, c]
    np.testing.assert_allclose(y, ref, rtol=1e-5, atol=1e-5)


def test_frames_per_group_bounds():
    assert dpt.frames_per_group(16, (168, 224), 2 * 168 * 224) == 2
    assert dpt.frames_per_group(16, (518, 518), 2 * 168 * 224) == 1  # never 0
    assert dpt.frames_per_group(3, (14, 14), 10**9) == 3  # never more than there are


def test_grouped_features_equal_ungrouped(setup, monkeypatch):
    config, io, aggregated, image_hw = setup
    params = load_head_params("track_head.feature_extractor", TRANSPOSED)
    tokens = {i: jnp.asarray(io[f"aggregated_{i:02d}"]) for i in config.track_layer_idx}

    def features():
        return np.asarray(jax.jit(lambda p, t: dpt.dpt_features(
            p, t, config.token_grid(image_hw), layer_idx=config.track_layer_idx))(params, tokens))

    whole = features()
    monkeypatch.setattr(dpt, "GROUP_PIXELS", 2 * 112 * 154)
    np.testing.assert_allclose(features(), whole, rtol=1e-5, atol=1e-5 * np.abs(whole).max())


@pytest.mark.parametrize("with_bias", [True, False])
def test_1x1_conv_as_matmul_equals_convolution(with_bias):
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.standard_normal((2, 5, 7, 6)).astype(np.float32))
    p = {"kernel": jnp.asarray(rng.standard_normal((1, 1, 6, 4)).astype(np.float32))}
    if with_bias:
        p["bias"] = jnp.asarray(rng.standard_normal(4).astype(np.float32))
    ref = jax.lax.conv_general_dilated(x, p["kernel"], (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    if with_bias:
        ref = ref + p["bias"]
    np.testing.assert_allclose(np.asarray(dpt.conv2d(p, x)), np.asarray(ref), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("outputs", [2, 4, 8, 9])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.bfloat16])
def test_relu_pointwise_equals_relu_then_1x1_conv(outputs, dtype):
    """The heads' last conv (ReLU, then a 1x1 conv with few outputs) as a multiply-reduce,
    against the ReLU and the convolution as written: the reduce up to 8 outputs, the matmul
    past them; x's dtype kept, products in float32 either way."""
    rng = np.random.default_rng(outputs)
    x = jnp.asarray(rng.standard_normal((2, 5, 7, 32)).astype(np.float32))
    p = {"kernel": jnp.asarray(rng.standard_normal((1, 1, 32, outputs)).astype(np.float32)),
         "bias": jnp.asarray(rng.standard_normal(outputs).astype(np.float32))}
    ref = jax.lax.conv_general_dilated(jax.nn.relu(x), p["kernel"], (1, 1), "VALID",
                                       dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                       precision=jax.lax.Precision.HIGHEST) + p["bias"]
    got = jax.jit(conv.relu_pointwise)(p, x.astype(dtype))
    assert got.shape == (2, 5, 7, outputs) and got.dtype == dtype
    # bf16: the input's own rounding (2^-9 relative) summed over 32 channels
    assert rel_err(got.astype(jnp.float32), ref) <= (1e-6 if dtype == jnp.float32 else 2e-2)
    assert conv.POINTWISE_REDUCE_MAX_OUT == 8  # the branch the outputs above straddle
    # the gradient too, exact zeros included (torch's ReLU passes none there)
    x0 = x.at[:, :, :3].set(0.0)
    r = jnp.asarray(rng.standard_normal((2, 5, 7, outputs)).astype(np.float32))
    g_ours = jax.grad(lambda t: jnp.sum(conv.relu_pointwise(p, t) * r))(x0)
    g_ref = jax.grad(lambda t: jnp.sum(dpt.conv2d(p, jax.nn.relu(t)) * r))(x0)
    assert rel_err(g_ours, g_ref) <= 1e-6 and not np.any(np.asarray(g_ours)[:, :, :3])
    # non-finite inputs as jax.nn.relu takes them (NaN kept, -inf to 0, +inf kept)
    xn = x.at[0, 0, 0, 0].set(jnp.nan).at[0, 1, 1, 1].set(-jnp.inf).at[1, 2, 2, 2].set(jnp.inf)
    ref_n = np.asarray(dpt.conv2d(p, jax.nn.relu(xn)))
    got_n = np.asarray(jax.jit(conv.relu_pointwise)(p, xn))
    np.testing.assert_array_equal(np.isnan(got_n), np.isnan(ref_n))
    np.testing.assert_array_equal(np.isinf(got_n), np.isinf(ref_n))
    assert np.isnan(got_n[0, 0, 0]).all() and np.isfinite(got_n[0, 1, 1]).all()
    fin = np.isfinite(ref_n)
    assert rel_err(got_n[fin], ref_n[fin]) <= 1e-6
    with pytest.raises(ValueError, match="1x1 kernel"):
        conv.relu_pointwise({"kernel": jnp.zeros((3, 3, 32, 2))}, x)


@pytest.mark.parametrize("channels, size", [((6, 4), (9, 11)), ((4, 4), (1, 7)), ((5, 3), (5, 6)), ((3, 5), (9, 11))])
@pytest.mark.parametrize("with_pos", [True, False])
def test_resized_conv3x3_equals_resize_then_conv(channels, size, with_pos):
    """The head's last upsampling and output_conv2's 3x3 conv as one map, against resize
    + positional map + conv: convolved at the low resolution when C >= O (an upsampling,
    a single output row, a map of the input's own size), as written when C < O."""
    c, o = channels
    rng = np.random.default_rng(c * 10 + o)
    x = jnp.asarray(rng.standard_normal((2, 5, 6, c)).astype(np.float32))
    p = {"kernel": jnp.asarray(rng.standard_normal((3, 3, c, o)).astype(np.float32)),
         "bias": jnp.asarray(rng.standard_normal(o).astype(np.float32))}
    pos = rng.standard_normal(size + (c,)).astype(np.float32) if with_pos else None
    ref = dpt.conv2d(p, resize.resize_bilinear_align_corners(x, size) + (0 if pos is None else pos))
    got = jax.jit(resize.resized_conv3x3(p, size, pos))(x)
    assert got.shape == (2,) + size + (o,)
    assert rel_err(got, ref) <= 1e-5


def test_resized_conv3x3_rejects_other_kernels_and_maps():
    with pytest.raises(ValueError, match="3x3 kernel"):
        resize.resized_conv3x3({"kernel": jnp.zeros((1, 1, 4, 4))}, (3, 3))
    with pytest.raises(ValueError, match="positional map"):
        resize.resized_conv3x3({"kernel": jnp.zeros((3, 3, 4, 4))}, (3, 3), np.zeros((2, 2, 4), np.float32))
    with pytest.raises(ValueError, match="k >= 2"):
        resize.patchwise_conv3x3({"kernel": jnp.zeros((1, 1, 4, 4)), "bias": jnp.zeros(4)},
                                 {"kernel": jnp.zeros((3, 3, 4, 4))}, (2, 2))


def test_wide_head_convolves_at_low_resolution_as_written(setup, monkeypatch):
    """A head as wide as VGGT-1B's last conv needs (features 64: output_conv1 32 -> 32
    channels, so the fused branch), in two groups of frames: the model's depth head
    against the same head with the upsampling and conv as written."""
    config, io, aggregated, image_hw = setup
    wide = dataclasses.replace(config, dpt_head=dataclasses.replace(config.dpt_head, features=64))
    shapes = jax.eval_shape(init_params, wide, jax.random.PRNGKey(0))["depth_head"]
    rng = np.random.default_rng(3)
    # kernels scaled by their fan-in, so that the activations stay O(1) through the head
    hp = {"depth_head": jax.tree.map(lambda a: jnp.asarray(
        rng.standard_normal(a.shape).astype(np.float32) / np.sqrt(np.prod(a.shape[:-1]))), shapes)}
    assert hp["depth_head"]["scratch"]["output_conv2"]["0"]["kernel"].shape[2:] == (32, 32)
    grid = wide.token_grid(image_hw)
    monkeypatch.setattr(dpt, "GROUP_PIXELS", 2 * image_hw[0] * image_hw[1])

    def as_written(p, size, pos=None):
        return lambda x: dpt.conv2d(p, resize.resize_bilinear_align_corners(x, size) + (0 if pos is None else pos))

    fused = jax.jit(lambda p, a: dpt.dense_heads(p, a, wide.dpt_head, grid))(hp, aggregated)
    monkeypatch.setattr(dpt, "resized_conv3x3", as_written)
    ref = jax.jit(lambda p, a: dpt.dense_heads(p, a, wide.dpt_head, grid))(hp, aggregated)
    for key in ref:
        assert rel_err(fused[key], ref[key]) <= 1e-5, key


@pytest.mark.parametrize("k, hw", [(4, (3, 5)), (2, (4, 3)), (4, (1, 2)), (2, (1, 1))])
@pytest.mark.parametrize("conv_bias", [False, True])
def test_patchwise_conv3x3_equals_upsample_then_conv(k, hw, conv_bias):
    """A level's x4 / x2 transposed conv and its 3x3 layer_rn as one map (composed
    kernels, <= 2 x 2 source pixels per output pixel), against the two convs in turn:
    maps of 1 to 5 pixels a side, so every border case of the zero padding is in."""
    rng = np.random.default_rng(k * 10 + hw[0])
    i_, m, o = 3, 5, 4
    x = jnp.asarray(rng.standard_normal((2,) + hw + (i_,)).astype(np.float32))
    up = {"kernel": jnp.asarray(rng.standard_normal((k, k, i_, m)).astype(np.float32)),
          "bias": jnp.asarray(rng.standard_normal(m).astype(np.float32))}
    conv = {"kernel": jnp.asarray(rng.standard_normal((3, 3, m, o)).astype(np.float32))}
    if conv_bias:
        conv["bias"] = jnp.asarray(rng.standard_normal(o).astype(np.float32))
    ref = dpt.conv2d(conv, dpt.conv_transpose_patchwise(up, x))
    got = jax.jit(resize.patchwise_conv3x3(up, conv, hw))(x)
    assert got.shape == (2, k * hw[0], k * hw[1], o)
    assert rel_err(got, ref) <= 1e-5
