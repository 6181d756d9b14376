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


# ---------------------------------------------------------------------------------------
# The sharded-forward checks run in a subprocess of their own (tests/_sharded_worker.py: 4
# host devices must be set before JAX starts). Started as soon as collection ends, so that
# it compiles alongside the rest of the suite (XLA compiles on one core), and read by
# tests/test_sharded.py.
# ---------------------------------------------------------------------------------------

_WORKER: dict = {}


def start_sharded_worker() -> None:
    import os
    import subprocess
    import sys
    import tempfile

    if "proc" in _WORKER:
        return
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out, err = tempfile.TemporaryFile(mode="w+"), tempfile.TemporaryFile(mode="w+")
    _WORKER.update(out=out, err=err, proc=subprocess.Popen(
        [sys.executable, str(Path(__file__).parent / "_sharded_worker.py")], env=env, stdout=out, stderr=err,
        text=True))


def sharded_worker_result(timeout: float = 1800) -> tuple[int, str, str]:
    """(return code, stdout, stderr) of the worker, started now if it was not."""
    start_sharded_worker()
    code = _WORKER["proc"].wait(timeout=timeout)
    _WORKER["out"].seek(0)
    _WORKER["err"].seek(0)
    return code, _WORKER["out"].read(), _WORKER["err"].read()


def pytest_collection_finish(session):
    if any(Path(str(item.fspath)).name == "test_sharded.py" for item in session.items):
        start_sharded_worker()


def pytest_sessionfinish(session, exitstatus):
    proc = _WORKER.get("proc")
    if proc is not None and proc.poll() is None:
        proc.kill()
