"""The chunk loops over tokens (`rvggt_jax.ops.chunks`): every loop equals one pass over
the whole sequence, in chunks that divide it or not (the last chunk overlapping the one
before), with plain and periodic inputs; an update in place changes every row once; the
`_through` loops hand the stream back unchanged; 16-bit slices go through bits exactly;
and the buffers made from data (`ops.ordering`) are what they claim."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import chunks, ordering


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


def test_row_chunk_size():
    assert chunks.row_chunks(1000, 16, 160) == 8  # at least 8 rows
    assert chunks.row_chunks(1000, 4, 400) == 96  # a multiple of 8 under the budget
    assert chunks.row_chunks(50, 4, 400) == 50  # everything fits: one chunk


def test_zeros_after_are_zeros_whatever_the_dependency_holds():
    for dep in (np.array([np.nan, 1.0]), np.array([np.inf]), np.array([-3.0])):
        z = jax.jit(lambda d: ordering.zeros_after((3, 2), jnp.bfloat16, d))(dep)
        assert z.dtype == jnp.bfloat16 and not np.any(np.asarray(z, np.float32))


def test_in_place_update_changes_every_row_exactly_once():
    # 100 rows in even chunks of 24 (5 chunks, the last overlapping the one before by 20
    # rows): a step that is not idempotent shows a row updated twice
    x = jnp.arange(2 * 100 * 3, dtype=jnp.float32).reshape(2, 100, 3)
    assert chunks.even_chunks(100, 24, 8) == (5, 24)
    out = jax.jit(lambda t: chunks.update_tokens(lambda c: c + 1.0, t, rows=24))(x)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(x) + 1.0)


@pytest.mark.parametrize("rows", [8, 24, 100])
def test_through_loops_return_the_stream_unchanged(rows):
    rng = np.random.default_rng(6)
    x = jnp.asarray(rng.standard_normal((2, 100, 6)).astype(np.float32))
    w = jnp.asarray(rng.standard_normal((6, 4)).astype(np.float32))

    def fn(t):
        return jnp.tanh(t @ w)

    xs, out = jax.jit(lambda t: chunks.map_tokens_through(fn, t, rows=rows))(x)
    np.testing.assert_array_equal(np.asarray(xs), np.asarray(x))
    np.testing.assert_allclose(np.asarray(out), np.asarray(fn(x)), rtol=1e-6, atol=1e-6)

    def step(acc, t):
        return acc + fn(t).sum(axis=1)

    xs, total = jax.jit(lambda t: chunks.fold_tokens_through(step, t, jnp.zeros((2, 4)), (), 100, rows))(x)
    np.testing.assert_array_equal(np.asarray(xs), np.asarray(x))
    np.testing.assert_allclose(np.asarray(total), np.asarray(fn(x).sum(axis=1)), rtol=1e-5, atol=1e-5)


def test_even_chunks_cover_every_row_without_a_short_tail():
    # rows as `row_chunks` gives them: a multiple of `multiple`
    for n in range(1, 130):
        for multiple, rows in ((1, 1), (1, 7), (1, 24), (8, 8), (8, 24), (8, 64)):
            count, size = chunks.even_chunks(n, rows, multiple)
            case = (n, rows, multiple)
            assert count == -(-n // rows) and count * size >= n and (count - 1) * size < n, case
            assert size == n or size % multiple == 0, case
            # chunk i starts at min(i * size, n - size): from 0, gapless, the last flush
            starts = [min(i * size, n - size) for i in range(count)]
            assert starts[0] == 0 and starts[-1] + size == n, case
            assert all(b - a <= size for a, b in zip(starts, starts[1:])), case


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_16bit_slices_and_gathers_equal_lax(dtype):
    # 16-bit operands are sliced and gathered as their bits (ops/bits.py): same values
    rng = np.random.default_rng(7)
    x = jnp.asarray(rng.standard_normal((4, 9, 3)), dtype)
    idx = jnp.asarray([5, 0, 8, 2])
    along = jnp.asarray(rng.integers(0, 9, (4, 6)))
    cases = [(chunks.dynamic_slice(x, jnp.int32(3), 4, 1), jax.lax.dynamic_slice_in_dim(x, 3, 4, 1)),
             (chunks.take(x, idx, 1), jnp.take(x, idx, axis=1)),
             (chunks.take_along(x, along, 1), jnp.take_along_axis(x, along[..., None], axis=1)),
             (chunks.dynamic_index(x, jnp.int32(2), 0), x[2])]
    for got, want in cases:
        assert got.dtype == dtype and got.shape == want.shape
        np.testing.assert_array_equal(np.asarray(got, np.float32), np.asarray(want, np.float32))


def test_ordered_after_leaves_the_value_unchanged():
    x = jnp.asarray([1.5, -2.0, 3.0e30], jnp.float32)
    deps = {"a": jnp.asarray([np.nan, 1.0]), "b": jnp.asarray([np.inf], jnp.bfloat16)}
    out = jax.jit(ordering.ordered_after)(x, deps)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(x))
