"""The parity metric."""

import numpy as np


def rel_err(ours, ref) -> float:
    """max |ours - ref| / max |ref|: the parity metric of every test."""
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape, (ours.shape, ref.shape)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())
