"""Shared fixtures: the tiny upstream checkpoint and its golden outputs (tests/data/vggt_tiny,
produced by the upstream PyTorch VGGT; see tests/data/README.md)."""

from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file

DATA = Path(__file__).parent / "data"
TINY = DATA / "vggt_tiny"


def rel_err(ours, ref) -> float:
    """max |ours - ref| / max |ref|: the parity metric of every test."""
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape, (ours.shape, ref.shape)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())


@pytest.fixture(scope="session")
def golden() -> dict[str, np.ndarray]:
    return load_file(TINY / "io.safetensors")


@pytest.fixture(scope="session")
def tiny():
    """(params, config) of the tiny checkpoint through the public loader."""
    import rvggt_jax

    return rvggt_jax.load_pretrained(TINY)
