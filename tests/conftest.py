"""Shared fixtures: the tiny upstream checkpoint and its golden outputs (tests/data/vggt_tiny,
produced by the upstream PyTorch VGGT; see tests/data/README.md). Plain helpers (paths,
`rel_err`, references) are in tests/helpers/."""

import gc
import os
from pathlib import Path

import jax
import numpy as np
import pytest
from safetensors.numpy import load_file

import rvggt_jax
from tests.helpers.allocator import preload_jemalloc
from tests.helpers.paths import REPO, TINY
from tests.helpers.sharded import (SHARDED_DIR_ENV, WORKER, remove_report_dir, start_sharded_worker,
                                   stop_sharded_worker)
from tests.helpers.xla_flags import suite_flags

# LLVM at -O0 for every program the suite compiles (tests/helpers/xla_flags.py: the same
# HLO and memory plans, about 40% less compile time); inherited by every subprocess.
os.environ["XLA_FLAGS"] = suite_flags(os.environ.get("XLA_FLAGS", ""))
# jemalloc for every process this one starts, when the machine has it
# (tests/helpers/allocator.py: XLA compiles in about 15% less CPU time than on glibc's malloc)
preload_jemalloc()
# Python's cycle collector, tuned for processes that trace thousands of programs: JAX's
# tracing makes millions of short-lived objects, so the default thresholds (a collection
# every 700 allocations, a full one every ~100 of those) walk the whole heap, JAX's modules
# and every test's live programs included, over and over. The objects alive after the
# imports are frozen (never walked again) and collections come 70x less often: 4.7 -> 1.3 s
# of collecting in tests/model/test_forward.py and test_merge.py (93 CPU-s). Garbage is still
# collected; `RVGGT_TEST_GC=default` keeps Python's defaults.
if os.environ.get("RVGGT_TEST_GC", "").lower() != "default":
    gc.freeze()
    gc.set_threshold(50_000, 20, 20)
# The suite runs CPU convolutions as the `rvggt` command does (multi-threaded; `import
# rvggt_jax` alone leaves XLA's default, tests/ops/test_xla_cpu.py): before any backend.
rvggt_jax.prefer_threaded_convolutions()
# The suite runs on the CPU. With the [plan] extra installed, JAX would also start its CUDA
# and TPU clients and warn that there is no such device; the deviceless compiles of
# tests/ops/test_kernel_choice.py need no client.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# libtpu (deviceless TPU compiles) holds a lock file per process: both xdist workers may
# compile for a TPU at once.
os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")
os.environ.setdefault("TPU_WORKER_HOSTNAMES", "localhost")


# One XLA compilation cache for the whole session, in a temporary folder: the same small
# programs (the tiny checkpoint's forward, above all) are compiled by many test files, by
# both pytest-xdist workers and by the `rvggt` subprocesses; each compiles once. Made by
# the session's first process (the workers and subprocesses inherit the variables).
if "RVGGT_TEST_XLA_CACHE" not in os.environ:
    import tempfile

    os.environ["RVGGT_TEST_XLA_CACHE"] = tempfile.mkdtemp(prefix="rvggt-test-xla-")
    os.environ["RVGGT_TEST_XLA_CACHE_OWNER"] = str(os.getpid())
os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["RVGGT_TEST_XLA_CACHE"]
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.2"
jax.config.update("jax_compilation_cache_dir", os.environ["RVGGT_TEST_XLA_CACHE"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


@pytest.fixture(scope="session")
def golden() -> dict[str, np.ndarray]:
    return load_file(TINY / "io.safetensors")


@pytest.fixture(scope="session")
def tiny():
    """(params, config) of the tiny checkpoint through the public loader."""
    return rvggt_jax.load_pretrained(TINY)


# ---------------------------------------------------------------------------------------
# The sharded-forward checks run in a subprocess of their own (tests/helpers/sharded.py):
# the session's first process starts it here, before the tests (and pytest-xdist's
# workers) start.
# ---------------------------------------------------------------------------------------

SHARDED_TESTS = tuple(REPO / "tests" / "parallel" / name for name in ("test_sharded.py", "test_sharded_train.py"))


def _selects_sharded(config) -> bool:
    """Whether the command line can run a test file reading the worker's report
    (SHARDED_TESTS, by path; -k may still deselect them, which only wastes the background
    run)."""
    targets = [t.resolve() for t in SHARDED_TESTS]
    args = [a.split("::")[0] for a in config.args] or [str(Path(__file__).parent)]
    for a in args:
        p = Path(a).resolve() if Path(a).is_absolute() else (Path(config.invocation_params.dir) / a).resolve()
        if any(p == t or (p.is_dir() and p in t.parents) for t in targets):
            return True
    return False


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session):
    import os

    if os.environ.get("PYTEST_XDIST_WORKER") or SHARDED_DIR_ENV in os.environ:
        return  # a pytest-xdist worker: the first process started it (and set the variable)
    if session.config.getoption("collectonly", False) or not _selects_sharded(session.config):
        return
    # inherited by pytest-xdist's workers, started after this
    os.environ[SHARDED_DIR_ENV] = start_sharded_worker()
    WORKER["owner"] = True


def pytest_sessionfinish(session, exitstatus):
    import os

    stop_sharded_worker()
    remove_report_dir()
    if WORKER.get("owner"):
        os.environ.pop(SHARDED_DIR_ENV, None)
    if os.environ.get("RVGGT_TEST_XLA_CACHE_OWNER") == str(os.getpid()):
        import shutil

        shutil.rmtree(os.environ["RVGGT_TEST_XLA_CACHE"], ignore_errors=True)


# ---------------------------------------------------------------------------------------
# RVGGT_TEST_COMPILE_LOG=path.jsonl: what each test compiles (tests/helpers/compile_log.py)
# ---------------------------------------------------------------------------------------

if os.environ.get("RVGGT_TEST_COMPILE_LOG"):
    from tests.helpers.compile_log import install as _install_compile_log

    _COMPILE_LOG = _install_compile_log(os.environ["RVGGT_TEST_COMPILE_LOG"])

    def _logged(phase):
        @pytest.hookimpl(hookwrapper=True)
        def hook(item):
            _COMPILE_LOG.start(item.nodeid, phase)
            yield
            _COMPILE_LOG.stop()

        return hook

    pytest_runtest_setup = _logged("setup")
    pytest_runtest_call = _logged("call")
    pytest_runtest_teardown = _logged("teardown")
