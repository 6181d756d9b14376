"""Attention building block: the blocked (cache-sized) evaluation equals the direct one."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax import layers


def _reference(q, k, v, bias=None):
    """softmax(q k^T / sqrt(d) + bias) v in float64 numpy, upstream's [B, H, N, D] layout."""
    q, k, v = (np.asarray(a, np.float64).transpose(0, 2, 1, 3) for a in (q, k, v))
    logits = q @ k.transpose(0, 1, 3, 2) / math.sqrt(q.shape[-1])
    if bias is not None:
        logits = logits + np.asarray(bias, np.float64)
    p = np.exp(logits - logits.max(-1, keepdims=True))
    return ((p / p.sum(-1, keepdims=True)) @ v).transpose(0, 2, 1, 3)


@pytest.mark.parametrize("block_bytes", [None, 4096, 40 * 4 * 3, 1])
@pytest.mark.parametrize("with_bias", [False, True])
def test_blocked_attention_equals_reference(block_bytes, with_bias):
    rng = np.random.default_rng(0)
    b, nq, nk, h, d = 2, 37, 45, 3, 8  # odd sizes: blocks are padded
    q = rng.standard_normal((b, nq, h, d)).astype(np.float32)
    k = rng.standard_normal((b, nk, h, d)).astype(np.float32)
    v = rng.standard_normal((b, nk, h, 5)).astype(np.float32)
    bias = rng.standard_normal((b, 1, 1, nk)).astype(np.float32) if with_bias else None
    out = jax.jit(lambda q, k, v, bias: layers.attention(q, k, v, bias, block_bytes=block_bytes))(q, k, v, bias)
    assert out.shape == (b, nq, h, 5)
    np.testing.assert_allclose(np.asarray(out), _reference(q, k, v, bias), rtol=1e-5, atol=1e-5)


def test_per_query_bias_is_honoured_even_when_blocks_are_small():
    rng = np.random.default_rng(1)
    q, k, v = (rng.standard_normal((1, 20, 2, 4)).astype(np.float32) for _ in range(3))
    bias = rng.standard_normal((1, 2, 20, 20)).astype(np.float32)
    out = layers.attention(q, k, v, bias, block_bytes=64)
    np.testing.assert_allclose(np.asarray(out), _reference(q, k, v, bias), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("nq, nk, budget", [(3152, 3152, 24 * 2**20), (100, 100, 10**9), (1000, 77, 4096), (5, 10**6, 1)])
def test_query_blocks_cover_all_rows_within_budget(nq, nk, budget):
    n, rows = layers.query_blocks(nq, nk, 4, budget)
    assert n * rows >= nq > (n - 1) * rows  # every row, no empty block
    if n > 1:
        assert rows % 8 == 0 and n * rows - nq < 8 * n
        # one block's logits stay within the budget, up to the 8-row rounding
        assert (rows - 7) * nk * 4 <= max(budget, 8 * nk * 4)
    else:
        assert rows == nq


def test_global_attention_size_uses_few_large_blocks():
    # The benchmark shape (16 frames x 197 tokens): 2 blocks of 1576 rows per head.
    assert layers.query_blocks(3152, 3152) == (2, 1576)


def test_attention_is_over_tokens_not_heads():
    # Permuting the heads permutes the output heads; permuting keys (with values) changes nothing.
    rng = np.random.default_rng(2)
    q, k, v = (jnp.asarray(rng.standard_normal((1, 30, 4, 8)).astype(np.float32)) for _ in range(3))
    out = layers.attention(q, k, v, block_bytes=256)
    perm = np.array([2, 0, 3, 1])
    np.testing.assert_allclose(layers.attention(q[:, :, perm], k[:, :, perm], v[:, :, perm], block_bytes=256),
                               out[:, :, perm], rtol=1e-5, atol=1e-6)
    keys = rng.permutation(30)
    np.testing.assert_allclose(layers.attention(q, k[:, keys], v[:, keys], block_bytes=256), out, rtol=1e-5, atol=1e-6)
