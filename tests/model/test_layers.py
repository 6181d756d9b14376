"""Building blocks: mixed precision of the linear / norm / MLP pieces; the RoPE tables of a
sequence (plain or periodic)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.model import layers
from rvggt_jax.ops import chunks


def test_linear_computes_in_the_input_dtype_with_float32_accumulation():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((4, 300)).astype(np.float32)
    p = {"kernel": rng.standard_normal((300, 7)).astype(np.float32), "bias": rng.standard_normal(7).astype(np.float32)}
    y32 = layers.linear(p, jnp.asarray(x))
    assert y32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(y32), x @ p["kernel"] + p["bias"], rtol=1e-5, atol=1e-4)
    y16 = layers.linear(p, jnp.asarray(x, jnp.bfloat16))
    assert y16.dtype == jnp.bfloat16
    # bf16 operands (8-bit mantissa), float32 sums: ~1e-2 relative, not the ~1e-1 of bf16 sums
    ref = np.asarray(jnp.asarray(x, jnp.bfloat16), np.float64) @ np.asarray(jnp.asarray(p["kernel"], jnp.bfloat16),
                                                                            np.float64) + p["bias"]
    assert np.abs(np.asarray(y16, np.float64) - ref).max() <= 1e-2 * np.abs(ref).max()


def test_layer_norm_statistics_in_float32_for_bfloat16_rows():
    # A wide row with a large mean: bfloat16 statistics would lose the small deviations.
    x = (1000.0 + np.linspace(-1, 1, 1024)).astype(np.float32)[None]
    out = layers.layer_norm(None, jnp.asarray(x, jnp.bfloat16), dtype=jnp.float32)
    xb = np.asarray(jnp.asarray(x, jnp.bfloat16), np.float64)
    ref = (xb - xb.mean()) / np.sqrt(xb.var() + 1e-5)
    np.testing.assert_allclose(np.asarray(out), ref, rtol=1e-4, atol=1e-4)
    assert layers.layer_norm(None, jnp.asarray(x, jnp.bfloat16)).dtype == jnp.bfloat16


@pytest.mark.parametrize("shape", [(64,), (5, 64), (2, 3, 64), (2, 3, 1, 64), (2, 3, 4, 1, 16)])
def test_layer_norm_of_any_rank_normalises_each_row(shape):
    """Rows of any rank (statistics over a [rows, C] view: the qk-norms' [B, N, H, D]),
    against a float64 reference, with the input's shape kept."""
    rng = np.random.default_rng(len(shape))
    x = (rng.standard_normal(shape) * 3 + 1).astype(np.float32)
    p = {"scale": rng.standard_normal(shape[-1]).astype(np.float32),
         "bias": rng.standard_normal(shape[-1]).astype(np.float32)}
    out = layers.layer_norm(p, jnp.asarray(x))
    assert out.shape == shape and out.dtype == jnp.float32
    x64 = x.astype(np.float64)
    ref = (x64 - x64.mean(-1, keepdims=True)) / np.sqrt(x64.var(-1, keepdims=True) + 1e-5) * p["scale"] + p["bias"]
    np.testing.assert_allclose(np.asarray(out), ref, rtol=1e-5, atol=1e-5)
    flat = layers.layer_norm(p, jnp.asarray(x.reshape(-1, shape[-1])))
    np.testing.assert_array_equal(np.asarray(out).reshape(-1, shape[-1]), np.asarray(flat))


def test_sequence_tables_are_one_frames_rows():
    # The sequence's tables are never tiled outside the blocks (every global block would
    # read the tiled tables from memory): one frame's rows, `chunks.Periodic`, at any
    # length; tiled, they are the frame's tables repeated.
    frame = layers.RopeTables.from_positions(jnp.asarray(layers.patch_positions(2, 3, 1))[None], 8, 100.0)
    seq = layers.RopeTables.of_sequence(frame, 4)
    assert isinstance(seq.cos, chunks.Periodic) and isinstance(seq.sin, chunks.Periodic)
    assert seq.cos.shape == (1, 28, 1, 8) and seq.cos.period.shape == (1, 7, 1, 8)
    for a, b in ((seq.cos.whole(), frame.cos), (seq.sin.whole(), frame.sin)):
        np.testing.assert_array_equal(np.asarray(a), np.tile(np.asarray(b), (1, 4, 1, 1)))
    tiled = layers.RopeTables(seq.cos.whole(), seq.sin.whole())
    # a frame's rows and the first rows, from the period and from the tiled tables
    local = jnp.asarray([[0, 6], [3, 1]])
    for t in (tiled, seq):
        np.testing.assert_array_equal(np.asarray(t.first(7).cos), np.asarray(frame.cos))
        np.testing.assert_array_equal(np.asarray(t.frame_rows(local).sin), np.asarray(frame.sin[0][local]))
    with pytest.raises(ValueError, match="8 rows asked of RoPE tables holding 7"):
        seq.first(8)
