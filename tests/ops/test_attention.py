"""The one attention op (rvggt_jax/ops/attention.py): the blocked CPU kernel and the
folded-bias `jax.nn.dot_product_attention` path against a float64 reference; key bias,
removed keys, bfloat16, memory that does not grow with the keys beyond K and V."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import attention as attn
from rvggt_jax.ops.kernels import blocked, fused
from tests.helpers.attention_reference import reference_attention


def _qkv(b=2, nq=37, nk=45, h=3, d=8, dv=8, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.standard_normal((b, nq, h, d)).astype(np.float32)
    k = rng.standard_normal((b, nk, h, d)).astype(np.float32)
    v = rng.standard_normal((b, nk, h, dv)).astype(np.float32)
    bias = np.log(np.floor(1 + 6 * rng.random((b, nk)))).astype(np.float32)  # log group sizes
    return q, k, v, bias


def _ref(q, k, v, bias=None):
    return reference_attention(q, k, v, None if bias is None else np.asarray(bias)[:, None, None, :])


@pytest.mark.parametrize("block_bytes", [None, 4096, 40 * 4 * 3, 1])
@pytest.mark.parametrize("with_bias", [False, True])
def test_blocked_equals_reference(block_bytes, with_bias):
    q, k, v, bias = _qkv(dv=5)  # odd sizes: blocks are padded; Dv != D
    bias = bias if with_bias else None
    out = jax.jit(lambda q, k, v, b: attn.attention(q, k, v, b, implementation="blocked",
                                                    block_bytes=block_bytes))(q, k, v, bias)
    assert out.shape == (2, 37, 3, 5) and out.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(out), _ref(q, k, v, bias), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("d", [8, 64])
@pytest.mark.parametrize("with_bias", [False, True])
def test_dot_product_attention_path_with_folded_bias(d, with_bias):
    # The GPU path (bias folded into an extra Q/K column) through XLA's implementation.
    q, k, v, bias = _qkv(d=d, dv=d)
    bias = bias if with_bias else None
    out = jax.jit(lambda q, k, v, b: attn.attention(q, k, v, b, implementation="xla"))(q, k, v, bias)
    np.testing.assert_allclose(np.asarray(out), _ref(q, k, v, bias), rtol=2e-5, atol=2e-5)


def test_fold_layout_pads_for_cudnn():
    q, k, v, bias = _qkv(d=64, dv=64)
    scale = 1 / math.sqrt(64)
    qf, kf, vf = fused.fold_key_bias(q, k, v, bias, scale, fused.CUDNN_HEAD_MULTIPLE)
    assert qf.shape[-1] == kf.shape[-1] == vf.shape[-1] == 72  # 64 + 1 -> a multiple of 8
    np.testing.assert_array_equal(np.asarray(qf[..., 64]), 1.0)
    np.testing.assert_allclose(np.asarray(kf[..., 64]), np.broadcast_to(bias[:, :, None] / scale, (2, 45, 3)),
                               rtol=1e-6)
    assert not np.any(np.asarray(qf[..., 65:])) and not np.any(np.asarray(kf[..., 65:]))
    assert not np.any(np.asarray(vf[..., 64:]))
    qf, kf, vf = fused.fold_key_bias(q, k, v, None, scale, fused.CUDNN_HEAD_MULTIPLE)
    assert qf.shape[-1] == 64  # no bias: nothing added


@pytest.mark.parametrize("implementation", ["blocked", "xla"])
def test_removed_keys_equal_dropping_them_and_stay_finite(implementation):
    q, k, v, g = _qkv(nk=30)
    sizes = np.exp(g)
    valid = np.random.default_rng(0).random((2, 30)) < 0.5
    valid[:, 0] = True
    lg = attn.log_sizes(jnp.asarray(sizes), jnp.asarray(valid))
    assert np.isfinite(np.asarray(lg)).all() and float(lg.min()) == attn.NEG_BIAS
    out = attn.attention(q, k, v, lg, implementation=implementation, block_bytes=256)
    for b in range(2):
        keep = np.flatnonzero(valid[b])
        ref = _ref(q[b:b + 1], k[b:b + 1, keep], v[b:b + 1, keep], np.log(sizes[b:b + 1, keep]))
        np.testing.assert_allclose(np.asarray(out[b:b + 1]), ref, rtol=2e-5, atol=2e-5)
    # every key removed: finite (uniform weights), never NaN
    none = attn.attention(q, k, v, attn.log_sizes(jnp.asarray(sizes), jnp.zeros((2, 30), bool)),
                          implementation=implementation)
    assert np.isfinite(np.asarray(none)).all()


def test_folded_bias_keeps_float32_precision_in_bfloat16():
    # hi + lo bfloat16 columns: the folded bias to ~2^-16, where one column keeps 2^-8
    bias = jnp.asarray(np.random.default_rng(3).uniform(-40, 40, (2, 500)), jnp.float32)
    cols = fused.bias_columns(bias, jnp.bfloat16)
    assert cols.shape == (2, 500, 2) and cols.dtype == jnp.bfloat16
    err = np.abs(np.asarray(cols.astype(jnp.float32).sum(-1)) - np.asarray(bias))
    assert err.max() <= 2.0**-15 * 40
    assert np.abs(np.asarray(bias.astype(jnp.bfloat16).astype(jnp.float32)) - np.asarray(bias)).max() > 2.0**-10 * 40
    assert fused.bias_columns(bias, jnp.float32).shape == (2, 500, 1)
    q, k, v, _ = _qkv(d=64, dv=64)
    qf, kf, vf = fused.fold_key_bias(*(jnp.asarray(t, jnp.bfloat16) for t in (q, k, v)), bias[:, :45], 0.125, 8)
    assert qf.shape[-1] == kf.shape[-1] == vf.shape[-1] == 72  # 64 + 2 -> a multiple of 8
    np.testing.assert_array_equal(np.asarray(qf[..., 64:66], np.float32), 1.0)
    assert not np.any(np.asarray(qf[..., 66:], np.float32)) and not np.any(np.asarray(kf[..., 66:], np.float32))


@pytest.mark.parametrize("implementation", ["blocked", "xla"])
def test_bfloat16_operands_float32_softmax(implementation):
    q, k, v, bias = _qkv(nq=64, nk=200, d=16, dv=16)
    bias = 3 * bias  # logits of the bias large enough for a bf16 rounding of it to show
    qb, kb, vb = (jnp.asarray(t, jnp.bfloat16) for t in (q, k, v))
    out = attn.attention(qb, kb, vb, jnp.asarray(bias), block_bytes=2048, implementation=implementation)
    assert out.dtype == jnp.bfloat16
    ref = _ref(*(np.asarray(t, np.float32) for t in (qb, kb, vb)), bias)  # the same rounded inputs
    # softmax and sums in float32, the bias exact (blocked) or a hi + lo pair (xla): only
    # the bf16 probabilities and output rounding remain (2e-3 and 3.5e-3 here; one
    # folded bf16 bias column gives 7e-3)
    assert np.abs(np.asarray(out, np.float64) - ref).max() <= 5e-3 * np.abs(ref).max()


@pytest.mark.parametrize("nq, nk, budget", [(3152, 3152, 24 * 2**20), (100, 100, 10**9), (1000, 77, 4096), (5, 10**6, 1)])
def test_query_blocks_cover_all_rows_within_budget(nq, nk, budget):
    n, rows = blocked.query_blocks(nq, nk, 4, budget)
    assert n * rows >= nq > (n - 1) * rows  # every row, no empty block
    if n > 1:
        assert rows % 8 == 0 and n * rows - nq < 8 * n
        # one block's logits stay within the budget, up to the 8-row rounding
        assert (rows - 7) * nk * 4 <= max(budget, 8 * nk * 4)
    else:
        assert rows == nq


def test_global_attention_size_uses_few_large_blocks():
    # The benchmark shape (16 frames x 197 tokens): 2 blocks of 1576 rows per head.
    assert blocked.query_blocks(3152, 3152) == (2, 1576)


def test_attention_is_over_tokens_not_heads():
    # Permuting the heads permutes the output heads; permuting keys (with values and
    # their bias) changes nothing.
    q, k, v, bias = _qkv(b=1, nq=30, nk=30, h=4)
    out = attn.attention(q, k, v, bias, block_bytes=256)
    perm = np.array([2, 0, 3, 1])
    np.testing.assert_allclose(attn.attention(q[:, :, perm], k[:, :, perm], v[:, :, perm], bias, block_bytes=256),
                               out[:, :, perm], rtol=1e-5, atol=1e-6)
    keys = np.random.default_rng(2).permutation(30)
    np.testing.assert_allclose(attn.attention(q, k[:, keys], v[:, keys], bias[:, keys], block_bytes=256), out,
                               rtol=1e-5, atol=1e-6)


def test_working_memory_does_not_grow_with_keys_beyond_k_and_v():
    # XLA's plan for 1 head of 64 and 2048 queries: 8x the keys adds ~8x K and V (and
    # their head-major copies), never the [Nq, Nk] logits (256 MiB at 32768 keys).
    def temp(nk):
        args = [jax.ShapeDtypeStruct((1, n, 1, 64), jnp.float32) for n in (2048, nk, nk)]
        args.append(jax.ShapeDtypeStruct((1, nk), jnp.float32))
        c = jax.jit(lambda q, k, v, b: attn.attention(q, k, v, b, implementation="blocked")).lower(*args).compile()
        return c.memory_analysis().temp_size_in_bytes

    small, large = temp(4096), temp(32768)
    kv_growth = 2 * (32768 - 4096) * 64 * 4
    assert large - small <= 3 * kv_growth
    assert large < blocked.LOGITS_BLOCK_BYTES * 2 + 4 * 32768 * 64 * 4 + 2048 * 64 * 4 * 4


@pytest.mark.parametrize("call, message", [
    (lambda q, k, v, b: attn.attention(q, k, v, implementation="flash"), "implementation"),
    (lambda q, k, v, b: attn.attention(q[0], k, v), "[B, N, H, D]"),
    (lambda q, k, v, b: attn.attention(q, k[:, :, :2], v), "disagree"),
    (lambda q, k, v, b: attn.attention(q, k, v, b[:, :3]), "key_bias"),
])
def test_bad_operands_are_named(call, message):
    q, k, v, bias = _qkv()
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        call(q, k, v, bias)
