"""Building blocks: mixed precision of the linear / norm / MLP pieces; row-chunked per-token
work."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import chunks, ordering

from rvggt_jax.model import layers


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


@pytest.mark.parametrize("rows", [1, 7, 8, 40, 100])
def test_token_chunks_equal_one_pass(rows):
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.standard_normal((2, 100, 6)).astype(np.float32))
    y = jnp.asarray(rng.standard_normal((1, 100, 6)).astype(np.float32))  # broadcast over the batch
    w = jnp.asarray(rng.standard_normal((6, 6)).astype(np.float32))

    def fn(t, u):
        return t + jnp.tanh(t @ w) * u

    def pair(t, u):
        return {"a": fn(t, u), "b": (t * u)[..., :2].astype(jnp.bfloat16)}

    ref = pair(x, y)
    out = jax.jit(lambda x, y: chunks.map_tokens(pair, (x, y), rows=rows))(x, y)
    np.testing.assert_allclose(np.asarray(out["a"]), np.asarray(ref["a"]), rtol=1e-6, atol=1e-6)
    assert out["b"].dtype == jnp.bfloat16 and out["b"].shape == (2, 100, 2)
    np.testing.assert_array_equal(np.asarray(out["b"], np.float32), np.asarray(ref["b"], np.float32))
    upd = jax.jit(lambda x, y: chunks.update_tokens(fn, x, (y,), rows=rows))(x, y)
    np.testing.assert_allclose(np.asarray(upd), np.asarray(fn(x, y)), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("rows", [8, 24, 100])
def test_periodic_rows_are_the_tiled_rows(rows):
    # One frame's rows held as a `chunks.Periodic` array (the RoPE tables of a long
    # sequence) stand for the rows tiled over the sequence: in every chunk loop, in chunks
    # that start inside a period and cross into the next (8, 24 rows over a period of 5),
    # and whole (100 rows: one chunk).
    rng = np.random.default_rng(5)
    period = jnp.asarray(rng.standard_normal((1, 5, 1, 6)).astype(np.float32))
    per, tiled = chunks.Periodic(period, 100), jnp.tile(period, (1, 20, 1, 1))
    assert per.shape == tiled.shape == (1, 100, 1, 6) and per.dtype == tiled.dtype
    np.testing.assert_array_equal(np.asarray(per.whole()), np.asarray(tiled))
    for start in (0, 3, 7, 93):
        got = jax.jit(lambda s: chunks.dynamic_slice(per, s, 7, 1))(jnp.int32(start))
        np.testing.assert_array_equal(np.asarray(got), np.asarray(tiled[:, start:start + 7]))
    np.testing.assert_array_equal(np.asarray(chunks.slice_rows(per, 96, 100, 1)), np.asarray(tiled[:, 96:]))

    x = jnp.asarray(rng.standard_normal((2, 100, 6)).astype(np.float32))

    def fn(t, c):
        return t * c[:, :, 0] + jnp.sin(t)

    for run in (lambda c: chunks.map_tokens(fn, (x, c), rows=rows),
                lambda c: chunks.update_tokens(fn, x, (c,), rows=rows),
                lambda c: chunks.map_tokens_through(fn, x, (c,), rows=rows)[1],
                lambda c: chunks.fold_tokens(lambda a, s, n, t, cc: a + fn(t, cc).sum(axis=1), jnp.zeros((2, 6)),
                                             (x, c), 100, 1, rows)):
        np.testing.assert_array_equal(np.asarray(jax.jit(run)(per)), np.asarray(jax.jit(run)(tiled)))
    with pytest.raises(ValueError, match="multiple of its period"):
        chunks.Periodic(period, 102)


def test_sequence_tables_are_periodic_only_when_long(monkeypatch):
    frame = layers.RopeTables.from_positions(jnp.asarray(layers.patch_positions(2, 3, 1))[None], 8, 100.0)
    short = layers.RopeTables.of_sequence(frame, 4)
    assert not isinstance(short.cos, chunks.Periodic) and short.cos.shape == (1, 28, 1, 8)
    monkeypatch.setattr(chunks, "TOKEN_CHUNK_BYTES", 28 * 8 * 4 - 1)
    long = layers.RopeTables.of_sequence(frame, 4)
    assert isinstance(long.cos, chunks.Periodic) and long.cos.shape == (1, 28, 1, 8)
    for a, b in ((long.cos.whole(), short.cos), (long.sin.whole(), short.sin)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a frame's rows and the first rows, from the period
    local = jnp.asarray([[0, 6], [3, 1]])
    for t in (short, long):
        np.testing.assert_array_equal(np.asarray(t.first(7).cos), np.asarray(frame.cos))
        np.testing.assert_array_equal(np.asarray(t.frame_rows(local).sin), np.asarray(frame.sin[0][local]))
    with pytest.raises(ValueError, match="8 rows asked of RoPE tables holding 7"):
        long.first(8)


def test_row_chunk_size():
    assert chunks.row_chunks(1000, 16, 160) == 8  # at least 8 rows
    assert chunks.row_chunks(1000, 4, 400) == 96  # a multiple of 8 under the budget
    assert chunks.row_chunks(50, 4, 400) == 50  # everything fits: one chunk


def test_zeros_from_are_zeros_whatever_the_dependency_holds():
    for dep in (np.array([np.nan, 1.0]), np.array([np.inf]), np.array([-3.0])):
        z = jax.jit(lambda d: ordering.zeros_from((3, 2), jnp.bfloat16, d))(dep)
        assert z.dtype == jnp.bfloat16 and not np.any(np.asarray(z, np.float32))
