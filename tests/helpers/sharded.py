"""The sharded-forward checks run in a subprocess of their own (tests/helpers/
sharded_worker.py: 4 host devices must be set before JAX starts). The session's first
process starts it before the tests (and pytest-xdist's workers) start (tests/conftest.py),
so that it compiles alongside the rest of the suite; tests/parallel/test_sharded.py waits
for its report in $RVGGT_SHARDED_DIR."""

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.helpers.paths import HELPERS
from tests.helpers.xla_flags import suite_flags

SHARDED_DIR_ENV = "RVGGT_SHARDED_DIR"
WORKER_SCRIPT = HELPERS / "sharded_worker.py"
WORKER: dict = {}  # "proc": the running worker; "owner": this process set $RVGGT_SHARDED_DIR; "dir": the
# report folder this process made (removed when its session ends)


def start_sharded_worker() -> str:
    """Run the worker in the background, reporting into a new folder (returned; removed
    by `remove_report_dir` when the session ends): its stdout, stderr and return code go
    to files there (out.json, err.txt, rc: written last)."""
    where = Path(tempfile.mkdtemp(prefix="rvggt-sharded-"))
    WORKER["dir"] = str(where)
    # (the worker sets its own device count; of the session's XLA flags it keeps only the
    # suite's compile options)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["XLA_FLAGS"] = suite_flags()
    launcher = ("import subprocess, sys; out, err, rc = sys.argv[2:5]; "
                "r = subprocess.run([sys.executable, sys.argv[1]], stdout=open(out, 'w'), stderr=open(err, 'w')); "
                "open(rc + '.tmp', 'w').write(str(r.returncode)); __import__('os').replace(rc + '.tmp', rc)")
    WORKER["proc"] = subprocess.Popen(
        [sys.executable, "-c", launcher, str(WORKER_SCRIPT),
         str(where / "out.json"), str(where / "err.txt"), str(where / "rc")], env=env,
        start_new_session=True)  # (a process group of its own: stop_sharded_worker ends the worker too)
    return str(where)


def stop_sharded_worker() -> None:
    """End the worker if it still runs (the launcher and the worker it started: killing
    the launcher alone left the worker computing after the session)."""
    import signal

    proc = WORKER.get("proc")
    if proc is not None and proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


def remove_report_dir() -> None:
    """Remove the report folder this process made, if any (after `stop_sharded_worker`)."""
    import shutil

    where = WORKER.pop("dir", None)
    if where is not None:
        shutil.rmtree(where, ignore_errors=True)


def sharded_worker_result(timeout: float = 1800) -> tuple[int, str, str]:
    """(return code, stdout, stderr) of the worker: the one the session started, or one
    run now."""
    where = os.environ.get(SHARDED_DIR_ENV)
    if where is None:  # (no worker started with the session: this process runs one, once)
        where = os.environ[SHARDED_DIR_ENV] = start_sharded_worker()
    where = Path(where)
    deadline = time.monotonic() + timeout
    while not (where / "rc").exists():
        if time.monotonic() > deadline:
            raise TimeoutError(f"the sharded worker wrote no report in {timeout} s")
        time.sleep(1.0)
    return int((where / "rc").read_text()), (where / "out.json").read_text(), (where / "err.txt").read_text()
