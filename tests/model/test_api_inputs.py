"""Inputs of the Python API that used to raise raw errors: a list of frames (under jit
too), an unknown compression preset."""

import jax
import numpy as np
import pytest

from rvggt_jax import InputError
from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.inputs import check_images
from tests.helpers import TINY

CONFIG = VGGTConfig.from_json(TINY / "config.json")


def test_list_of_frames_is_stacked_eager_and_under_jit():
    frames = [np.full((3, 28, 42), i / 4, np.float32) for i in range(3)]
    out = check_images(frames, CONFIG)
    assert out.shape == (1, 3, 3, 28, 42)
    np.testing.assert_array_equal(np.asarray(out[0, 2]), frames[2])
    traced = jax.eval_shape(lambda xs: check_images(xs, CONFIG), frames)  # a list of tracers
    assert traced.shape == (1, 3, 3, 28, 42)


@pytest.mark.parametrize("frames, needle", [([], "an empty list"),
                                            ([np.zeros((3, 28, 28)), np.zeros((3, 14, 28))], "(3, 14, 28)")])
def test_unstackable_frames_refused(frames, needle):
    with pytest.raises(InputError, match=r"one array \[S,3,H,W\]") as e:
        check_images(frames, CONFIG)
    assert needle in str(e.value)


def test_unknown_preset_is_an_input_error():
    with pytest.raises(InputError, match="unknown compression preset 'nope'; known: "):
        CONFIG.with_compression("nope")
    with pytest.raises(InputError, match="unknown compression fields"):
        CONFIG.with_compression("regime", not_a_field=1)
