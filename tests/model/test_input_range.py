"""Images outside [0, 1] or with NaN: an `InputRangeWarning` (a float image is legal, so
only its values tell), checked at once for concrete arrays and from inside the compiled
program under jit (no second compile, no host sync in the caller), except with JAX's
persistent compilation cache on: a host callback would keep the program out of it."""

import contextlib

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rvggt_jax
from rvggt_jax import InputRangeWarning, rvggt_forward
from rvggt_jax.model.inputs import check_inputs

SHAPE = (1, 1, 3, 14, 14)  # one patch: the smallest forward


def _images(kind):
    x = np.random.default_rng(0).random(SHAPE, dtype=np.float32)
    if kind == "0..255":
        return x * 255.0  # a forgotten / 255
    if kind == "nan":
        x[0, 0, 1, 3, 4] = np.nan
        x[0, 0, 2, 5, 6] = np.nan
        return x
    if kind == "negative":
        return x - 0.5
    return x


def test_warning_is_a_user_warning_exported_by_the_package():
    assert issubclass(rvggt_jax.InputRangeWarning, UserWarning)


@pytest.mark.parametrize("kind, expected", [
    ("0..255", r"values in \[\d.*, 2\d\d.*\].*expects float RGB in \[0, 1\].*divide by 255"),
    ("nan", r"2 NaN value"),
    ("negative", r"values in \[-0\.\d+, 0\.\d+\]"),
])
@pytest.mark.parametrize("array", [np.asarray, jnp.asarray])
def test_concrete_images_out_of_range_warn(tiny, kind, expected, array):
    params, config = tiny
    with pytest.warns(InputRangeWarning, match=expected):
        check_inputs(params, array(_images(kind)), config)


@pytest.mark.parametrize("images", [_images("ok"), np.zeros(SHAPE, np.float32), np.ones(SHAPE, np.float32),
                                    np.zeros(SHAPE, jnp.bfloat16)])
def test_concrete_images_in_range_stay_silent(tiny, images):
    params, config = tiny
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_inputs(params, images, config)


def test_empty_images_are_refused_by_the_shape_check_not_the_range_check(tiny):
    params, config = tiny
    with pytest.raises(rvggt_jax.InputError, match="empty axis"):
        check_inputs(params, np.zeros((1, 0, 3, 14, 14), np.float32), config)


@contextlib.contextmanager
def _persistent_cache(directory):
    """JAX's persistent compilation cache at `directory` (None: off) for the block (the
    suite runs with it on: tests/conftest.py)."""
    saved = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", directory)
    try:
        yield
    finally:
        jax.config.update("jax_compilation_cache_dir", saved)


@pytest.fixture
def without_persistent_cache():
    with _persistent_cache(None):
        yield


def test_under_jit_the_program_warns_and_compiles_once(tiny, without_persistent_cache):
    params, config = tiny
    # a function of its own: jax.jit(rvggt_forward) would share its cache with the other
    # tests' jax.jit(rvggt_forward) in this process
    fwd = jax.jit(lambda p, x, config: rvggt_forward(p, x, config), static_argnames="config")
    with pytest.warns(InputRangeWarning, match=r"divide by 255"):
        jax.block_until_ready(fwd(params, _images("0..255"), config=config))
        jax.effects_barrier()  # the host callback has run
    with pytest.warns(InputRangeWarning, match=r"2 NaN value"):
        jax.block_until_ready(fwd(params, _images("nan"), config=config))
        jax.effects_barrier()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # valid input: silent
        out = fwd(params, _images("ok"), config=config)
        jax.block_until_ready(out)
        jax.effects_barrier()
    assert np.isfinite(np.asarray(out["depth"])).all()
    assert fwd._cache_size() == 1  # the values never reach the trace: one program for all three


def test_with_the_persistent_cache_on_the_program_holds_no_callback(tiny, tmp_path):
    """JAX does not store programs with host callbacks in its persistent cache: with the
    cache on (as `rvggt` runs) the traced program leaves the check out, so that it is
    stored; with it off the check is in."""
    params, config = tiny

    def program_text():  # a fresh function each time: jit caches its trace, not the setting
        return jax.jit(lambda p, x: rvggt_forward(p, x, config)).lower(params, _images("ok")).as_text()

    with _persistent_cache(None):
        assert rvggt_jax.model.input_range.program_check_enabled()
        assert "callback" in program_text()
    with _persistent_cache(str(tmp_path)):
        assert not rvggt_jax.model.input_range.program_check_enabled()
        assert "callback" not in program_text()


def test_under_jit_one_nan_warns_whatever_the_shape(without_persistent_cache):
    """XLA's CPU min/max drop NaN for some shapes (this one among them): the traced check
    counts NaNs itself."""
    from rvggt_jax.model.input_range import warn_if_out_of_range

    x = np.random.default_rng(0).random((2, 3, 28, 28), dtype=np.float32)
    x[1, 2, 3, 4] = np.nan
    check = jax.jit(lambda a: (warn_if_out_of_range(a), a * 2)[1])
    with pytest.warns(InputRangeWarning, match=r"1 NaN value"):
        jax.block_until_ready(check(x))
        jax.effects_barrier()
