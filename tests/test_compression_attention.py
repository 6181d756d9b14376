"""Size-biased attention: the folded Q/K column equals an explicit additive log g bias;
padding, chunking and empty (masked) slots."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax import layers
from rvggt_jax.compression import attention as attn_lib
from rvggt_jax.compression.attention import NEG_LOG, fold_size_bias, log_sizes

# jitted (static sizes), so the tests do not dispatch op by op
size_biased_attention = jax.jit(attn_lib.size_biased_attention, static_argnums=(4, 5))
core_attention = jax.jit(attn_lib.core_attention, static_argnums=(3, 4))


def _qkv(b=2, nq=37, nk=23, h=2, d=16, seed=0):
    k1, k2, k3, k4 = jax.random.split(jax.random.PRNGKey(seed), 4)
    q = jax.random.normal(k1, (b, nq, h, d))
    k = jax.random.normal(k2, (b, nk, h, d))
    v = jax.random.normal(k3, (b, nk, h, d))
    g = jnp.floor(1 + 6 * jax.random.uniform(k4, (b, nk)))
    return q, k, v, g


@pytest.mark.parametrize("pad", [1, 8, 16])
@pytest.mark.parametrize("chunk", [0, 8])
def test_folded_equals_explicit_bias(pad, chunk):
    q, k, v, g = _qkv()
    ref = layers.attention(q, k, v, bias=jnp.log(g)[:, None, None, :])
    out = size_biased_attention(q, k, v, jnp.log(g), pad, chunk)
    np.testing.assert_allclose(out, ref, rtol=2e-5, atol=2e-6)


def test_fold_layout():
    q, k, v, g = _qkv(d=64)
    qf, kf, vf = fold_size_bias(q, k, v, jnp.log(g), 16)
    assert qf.shape[-1] == kf.shape[-1] == vf.shape[-1] == 80  # 64 -> 80, the GPU flash size
    np.testing.assert_array_equal(qf[..., 64], 1.0)
    np.testing.assert_allclose(kf[..., 64], math.sqrt(64) * jnp.log(g)[:, :, None] * jnp.ones(2), rtol=1e-6)
    assert not np.any(qf[..., 65:]) and not np.any(kf[..., 65:]) and not np.any(vf[..., 64:])
    qf, kf, vf = fold_size_bias(q, k, v, jnp.log(g), 1)
    assert qf.shape[-1] == 65 and vf.shape[-1] == 64


def test_unit_sizes_equal_plain_attention():
    q, k, v, _ = _qkv()
    ref = layers.attention(q, k, v)
    np.testing.assert_allclose(size_biased_attention(q, k, v, jnp.zeros(k.shape[:2]), 1, 0), ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(size_biased_attention(q, k, v, None, 1, 8), ref, rtol=1e-5, atol=1e-6)


def test_masked_slots_equal_dropping_them_and_stay_finite():
    q, k, v, g = _qkv(nk=30)
    valid = jnp.asarray(np.random.default_rng(0).random((2, 30)) < 0.5).at[:, 0].set(True)
    out = size_biased_attention(q, k, v, log_sizes(g, valid), 1, 8)
    for b in range(2):
        keep = np.flatnonzero(np.asarray(valid[b]))
        ref = layers.attention(q[b:b + 1], k[b:b + 1, keep], v[b:b + 1, keep], bias=jnp.log(g[b, keep])[None, None, None])
        np.testing.assert_allclose(out[b:b + 1], ref, rtol=2e-5, atol=2e-6)
    lg = log_sizes(g, valid)
    assert np.isfinite(np.asarray(lg)).all() and float(lg.min()) == NEG_LOG
    # every slot empty: still finite (uniform weights), never NaN
    allmask = size_biased_attention(q, k, v, log_sizes(g, jnp.zeros_like(valid)), 1, 0)
    assert np.isfinite(np.asarray(allmask)).all()


def test_chunked_core_equals_unchunked():
    q, k, v, _ = _qkv(nq=50)
    a = core_attention(q, k, v, 0.25, 0)
    for chunk in (7, 16, 50, 64):
        np.testing.assert_allclose(core_attention(q, k, v, 0.25, chunk), a, rtol=1e-5, atol=1e-6)
