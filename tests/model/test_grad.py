"""Gradients through `rvggt_forward`: finite and non-zero for every parameter the loss
reaches (dense and the compression presets: merging and K/V selection are index
operations, gradients flow through the values), float64 finite differences, and the
bfloat16 slices of `rvggt_jax.ops.chunks` (bit views) pass gradients."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rvggt_jax
from rvggt_jax.ops import bits, chunks
from rvggt_jax.compression.config import PRESETS
from rvggt_jax.model.forward import rvggt_forward
from tests.helpers import HELPERS, REPO
from tests.helpers.micro import micro_config

# dense and regime always; every other preset compiles one more gradient (~20 s each on
# 2 cores): RVGGT_TEST_ALL_PRESETS=1 runs them too
DEFAULT_PRESETS = ("dense", "regime")
ALL = bool(os.environ.get("RVGGT_TEST_ALL_PRESETS"))
# Parameters no output depends on: DINO's mask token (masked pre-training only).
UNUSED = {"aggregator/patch_embed/mask_token"}


@pytest.fixture(scope="module")
def setup():
    config = micro_config(enable_point=False, enable_track=False)
    params = rvggt_jax.init_params(config, 2)
    images = jnp.asarray(np.random.default_rng(0).random((1, 3, 3, 28, 42)), jnp.float32)
    return config, params, images


@pytest.mark.parametrize("preset", [p if p in DEFAULT_PRESETS or ALL else
                                    pytest.param(p, marks=pytest.mark.skip("RVGGT_TEST_ALL_PRESETS=1 runs it"))
                                    for p in PRESETS])
def test_gradients_are_finite_and_reach_every_parameter(setup, preset):
    config, params, images = setup
    cfg = config.with_compression(preset)

    def loss(p):
        out = rvggt_forward(p, images, cfg)
        # every camera iteration (later ones detach the earlier encoding, as upstream)
        return sum(jnp.sum(e ** 2) for e in out["pose_enc_list"]) + jnp.mean(out["depth"][..., 0] * out["depth_conf"])

    grads = jax.jit(jax.grad(loss))(params)
    flat = {"/".join(k.key for k in path): np.asarray(g) for path, g in jax.tree_util.tree_leaves_with_path(grads)}
    assert all(np.isfinite(g).all() for g in flat.values())
    zero = sorted(k for k, g in flat.items() if not np.any(g) and k not in UNUSED)
    assert zero == [], f"{preset}: no gradient reaches {zero}"
    assert all(not np.any(flat[k]) for k in UNUSED)


def test_float64_finite_differences():
    """Directional derivative of jax.grad vs central differences, float64 (a subprocess:
    x64 must be on before JAX starts; see tests/helpers/grad_fd.py), relative error <= 1e-5."""
    script = HELPERS / "grad_fd.py"
    env = dict(os.environ, JAX_ENABLE_X64="1")
    r = subprocess.run([sys.executable, str(script), *DEFAULT_PRESETS], capture_output=True, text=True, env=env,
                       cwd=REPO, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(res) == set(DEFAULT_PRESETS)
    for preset, v in res.items():
        assert abs(v["numeric"]) > 1e-3, v  # a derivative that is not trivially zero
        assert v["rel_err"] <= 1e-5, (preset, v)


@pytest.mark.parametrize("dtype", ["bfloat16", "float16"])
def test_16bit_bit_view_slices_pass_gradients(dtype):
    """chunks' 16-bit slices and gathers go through uint16 views (for XLA:CPU); their
    gradients must equal those of the plain float32 ops, not vanish."""
    x32 = jnp.asarray(np.random.default_rng(3).standard_normal((5, 4)), jnp.float32)
    x = x32.astype(dtype)
    w = jnp.arange(1.0, 9.0).reshape(2, 4)
    idx = jnp.array([4, 0])
    along = jnp.array([[1], [0], [3], [2], [0]])
    cases = [(lambda t: chunks.dynamic_slice(t, jnp.int32(2), 2, 0), lambda t: jax.lax.dynamic_slice_in_dim(t, 2, 2, 0)),
             (lambda t: chunks.take(t, idx, 0), lambda t: jnp.take(t, idx, axis=0)),
             (lambda t: chunks.take_along(t, along, 1)[:2], lambda t: jnp.take_along_axis(t, along, 1)[:2])]
    for ours, plain in cases:
        np.testing.assert_array_equal(np.asarray(ours(x).astype(jnp.float32)), np.asarray(plain(x32).astype(x.dtype)
                                                                                         .astype(jnp.float32)))
        g = jax.jit(jax.grad(lambda t: jnp.sum(ours(t).astype(jnp.float32) * w[:, :ours(t).shape[1]])))(x)
        want = jax.grad(lambda t: jnp.sum(plain(t) * w[:, :plain(t).shape[1]]))(x32)
        assert np.any(np.asarray(want))
        np.testing.assert_array_equal(np.asarray(g.astype(jnp.float32)), np.asarray(want))  # small integers: exact


@pytest.mark.parametrize("dtype", ["bfloat16", "float16"])
def test_bits16_buffer_passes_gradients(dtype):
    """A 16-bit buffer held as bits (bits.HalfBuffer, the aggregator's kept layers): writes
    and reads must pass the gradients of the plain float ops (through its shadow)."""
    x32 = jnp.asarray(np.random.default_rng(4).standard_normal((3, 2, 4)), jnp.float32)
    w = jnp.arange(1.0, 9.0).reshape(2, 4)

    def ours(t):
        buf = bits.HalfBuffer.zeros_after((3, 2, 4), dtype, t)
        for k in range(3):
            buf = buf.update_index(t[k] * (k + 1), jnp.int32(k))
        return buf.read(lambda b, i: jax.lax.dynamic_index_in_dim(b, i, 0, keepdims=False), jnp.int32(1))

    def plain(t):
        return (t[1] * 2).astype(dtype)

    x = x32.astype(dtype)
    np.testing.assert_array_equal(np.asarray(ours(x).astype(jnp.float32)), np.asarray(plain(x).astype(jnp.float32)))
    g = jax.jit(jax.grad(lambda t: jnp.sum(ours(t).astype(jnp.float32) * w)))(x)
    want = jax.grad(lambda t: jnp.sum(plain(t).astype(jnp.float32) * w))(x)
    assert np.any(np.asarray(want, np.float32))
    np.testing.assert_array_equal(np.asarray(g, np.float32), np.asarray(want, np.float32))
