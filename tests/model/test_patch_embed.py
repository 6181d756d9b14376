"""Patch embed (DINOv2) and saliency Psi against the upstream fixture, and the
position-table interpolation against torch's antialiased bicubic."""

import numpy as np
import pytest

from tests.helpers import DATA, rel_err
from rvggt_jax.model.patch_embed import bicubic_aa_matrix, interpolate_pos_embed


@pytest.mark.parametrize("key", [k for k in np.load(DATA / "interp_bicubic_aa.npz").files if k != "grid"])
def test_pos_embed_interpolation_matches_torch(key):
    data = np.load(DATA / "interp_bicubic_aa.npz")
    grid = data["grid"][0]  # [C, 37, 37]
    hw, offset = key.split("@")
    h, w = map(int, hw.split("x"))
    c = grid.shape[0]
    table = np.concatenate([np.zeros((1, c)), grid.reshape(c, -1).T])[None].astype(np.float32)
    out = np.asarray(interpolate_pos_embed(table, h, w, float(offset)))
    ours = out[0, 1:].reshape(h, w, c).transpose(2, 0, 1)
    assert rel_err(ours, data[key][0]) < 1e-5


def test_interpolation_weights_are_normalised_and_local():
    m = bicubic_aa_matrix(37, 8)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-6)
    # shrinking 37 -> 8 widens the support to ~2*37/8 taps on each side, no further
    assert (np.count_nonzero(m, axis=1) <= 2 * int(np.ceil(2 * 37 / 8)) + 1).all()
    np.testing.assert_array_equal(bicubic_aa_matrix(37, 37, 37 / 37.1), np.eye(37))
