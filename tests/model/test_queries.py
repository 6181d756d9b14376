"""Query points as users write them: lists, NumPy (int or float), JAX; clear errors."""

import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax import InputError, as_query_points


@pytest.mark.parametrize("q", [[[100.0, 200.0], [60, 259]], ((1, 2),), np.array([[100, 200]]),
                               np.array([[[1.5, 2.5]]], np.float64), jnp.zeros((2, 3, 2), jnp.int32)])
def test_accepted(q):
    a = as_query_points(q)
    assert a.dtype == jnp.float32 and a.shape == np.shape(q)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(q, np.float32))


@pytest.mark.parametrize("q, needle", [("ab", "got a str"), ({"x": 1}, "got a dict"), ([[1, 2], [3]], "cannot read"),
                                       ([[1, 2, 3]], "shape (1, 3)"), ([1, 2], "shape (2,)"),
                                       (np.array([[True, False]]), "dtype bool"),
                                       (np.array([["a", "b"]]), "")])
def test_rejected(q, needle):
    with pytest.raises(InputError, match="query_points are pixel") as e:
        as_query_points(q)
    assert needle in str(e.value)


@pytest.mark.parametrize("q, needle", [([[np.nan, 3], [10, 10]], "point 0 is [nan, 3.0]"),
                                       ([[[1, 2], [np.inf, 3]]], "point (0, 1) is [inf, 3.0]"),
                                       (np.zeros((0, 2)), "got no points (shape (0, 2))"),
                                       (np.zeros((1, 0, 2)), "got no points")])
def test_non_finite_or_no_points_rejected(q, needle):
    """A NaN point would make every other point's visibility NaN; no points divided by zero."""
    with pytest.raises(InputError, match="query_points are pixel") as e:
        as_query_points(q)
    assert needle in str(e.value)
