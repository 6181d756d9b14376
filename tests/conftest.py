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
# host devices must be set before JAX starts). The session's first process starts it
# before the tests (and pytest-xdist's workers) start, so that it compiles alongside the
# rest of the suite; tests/test_sharded.py waits for its report in $RVGGT_SHARDED_DIR.
# ---------------------------------------------------------------------------------------

SHARDED_DIR_ENV = "RVGGT_SHARDED_DIR"
_WORKER: dict = {}


def start_sharded_worker(where: Path) -> None:
    """Run the worker in the background: its stdout, stderr and return code go to files
    in `where` (out.json, err.txt, rc: written last)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    launcher = ("import subprocess, sys; out, err, rc = sys.argv[2:5]; "
                "r = subprocess.run([sys.executable, sys.argv[1]], stdout=open(out, 'w'), stderr=open(err, 'w')); "
                "open(rc + '.tmp', 'w').write(str(r.returncode)); __import__('os').replace(rc + '.tmp', rc)")
    _WORKER["proc"] = subprocess.Popen(
        [sys.executable, "-c", launcher, str(Path(__file__).parent / "_sharded_worker.py"),
         str(where / "out.json"), str(where / "err.txt"), str(where / "rc")], env=env)


def sharded_worker_result(timeout: float = 1800) -> tuple[int, str, str]:
    """(return code, stdout, stderr) of the worker: the one the session started, or one
    run now."""
    import os
    import tempfile
    import time

    where = os.environ.get(SHARDED_DIR_ENV)
    if where is None:
        where = tempfile.mkdtemp(prefix="rvggt-sharded-")
        start_sharded_worker(Path(where))
    where = Path(where)
    deadline = time.monotonic() + timeout
    while not (where / "rc").exists():
        if time.monotonic() > deadline:
            raise TimeoutError(f"the sharded worker wrote no report in {timeout} s")
        time.sleep(1.0)
    return int((where / "rc").read_text()), (where / "out.json").read_text(), (where / "err.txt").read_text()


def _selects_sharded(config) -> bool:
    """Whether the command line can run tests/test_sharded.py (by path; -k may still
    deselect it, which only wastes the background run)."""
    target = (Path(__file__).parent / "test_sharded.py").resolve()
    args = [a.split("::")[0] for a in config.args] or [str(Path(__file__).parent)]
    for a in args:
        p = Path(a).resolve() if Path(a).is_absolute() else (Path(config.invocation_params.dir) / a).resolve()
        if p == target or (p.is_dir() and p in target.parents):
            return True
    return False


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session):
    import os
    import tempfile

    if os.environ.get("PYTEST_XDIST_WORKER") or SHARDED_DIR_ENV in os.environ:
        return  # a pytest-xdist worker: the first process started it (and set the variable)
    if session.config.getoption("collectonly", False) or not _selects_sharded(session.config):
        return
    where = tempfile.mkdtemp(prefix="rvggt-sharded-")
    os.environ[SHARDED_DIR_ENV] = where  # inherited by pytest-xdist's workers, started after this
    _WORKER["owner"] = True
    start_sharded_worker(Path(where))


def pytest_sessionfinish(session, exitstatus):
    import os

    proc = _WORKER.get("proc")
    if proc is not None and proc.poll() is None:
        proc.kill()
    if _WORKER.get("owner"):
        os.environ.pop(SHARDED_DIR_ENV, None)
