"""Camera head parity with the upstream PyTorch outputs of the tiny fixture."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.heads.camera import activate_pose, camera_head
from tests.helpers import TINY, rel_err
from tests.helpers.heads_params import load_head_params, load_io

RTOL = 1e-4


@pytest.fixture(scope="module")
def setup():
    config = VGGTConfig.from_json(TINY / "config.json")
    io = load_io()
    params = load_head_params("camera_head")
    last = io[f"aggregated_{config.depth - 1:02d}"]
    run = jax.jit(camera_head, static_argnums=2)
    return config, io, params, last, run


def test_every_iteration_matches_upstream(setup):
    config, io, params, last, run = setup
    outs = run(params, jnp.asarray(last), config.camera_head)
    ref_list = io["pose_enc_list"]
    assert len(outs) == config.camera_head.iters == ref_list.shape[0]
    errs = [rel_err(o, r) for o, r in zip(outs, ref_list)]
    print("camera head rel errors per iteration:", errs)
    assert max(errs) <= RTOL, errs
    assert rel_err(outs[-1], io["pose_enc"]) <= RTOL
    # Refinement must actually move the prediction, or the per-iteration check is weak.
    assert rel_err(ref_list[0], ref_list[-1]) > 1e-2


def test_fov_relu_is_applied(setup):
    config, _, params, last, run = setup
    # A large negative bias on the FoV outputs of the pose branch: relu clamps them to 0.
    p = jax.tree_util.tree_map(lambda x: x, params)
    bias = np.array(p["pose_branch"]["fc2"]["bias"])
    bias[7:] = -1e3
    p["pose_branch"]["fc2"]["bias"] = bias
    out = run(p, jnp.asarray(last), config.camera_head)[0]
    np.testing.assert_array_equal(np.asarray(out[..., 7:]), 0.0)
    assert np.all(np.asarray(out[..., :7]) != 0.0)


def test_refinement_feeds_back_the_raw_encoding(setup):
    # Every FoV of the fixture is relu-clamped to 0, so its FoV outputs alone say little.
    # With a linear FoV activation the raw encodings appear; since each iteration is fed
    # the raw (not the activated) running sum, relu of them must give the fixture exactly.
    config, io, params, last, run = setup
    linear = run(params, jnp.asarray(last), dataclasses.replace(config.camera_head, fl_act="linear"))
    assert np.all(io["pose_enc_list"][..., 7:] == 0) and np.any(np.asarray(linear[0][..., 7:]) < -1e-3)
    for out, ref in zip(linear, io["pose_enc_list"]):
        relu = np.concatenate([np.asarray(out[..., :7]), np.maximum(np.asarray(out[..., 7:]), 0)], axis=-1)
        assert rel_err(relu, ref) <= RTOL


def test_iteration_count_follows_config(setup):
    config, io, params, last, run = setup
    two = dataclasses.replace(config.camera_head, iters=2)
    outs = run(params, jnp.asarray(last), two)
    assert len(outs) == 2
    assert rel_err(outs[1], io["pose_enc_list"][1]) <= RTOL


def test_activate_pose_parts():
    x = jnp.asarray(np.linspace(-2, 2, 18, dtype=np.float32).reshape(2, 9))
    y = np.asarray(activate_pose(x, trans_act="inv_log", quat_act="exp", fl_act="relu"))
    xn = np.asarray(x)
    np.testing.assert_allclose(y[:, :3], np.sign(xn[:, :3]) * np.expm1(np.abs(xn[:, :3])), rtol=1e-6)
    np.testing.assert_allclose(y[:, 3:7], np.exp(xn[:, 3:7]), rtol=1e-6)
    np.testing.assert_allclose(y[:, 7:], np.maximum(xn[:, 7:], 0), rtol=1e-6)
    with pytest.raises(ValueError):
        activate_pose(x, trans_act="nope")
