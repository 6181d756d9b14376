"""Ctrl-C while the model runs (issue 53): the forward runs in a worker thread, so the
interrupt reaches the command at once instead of when XLA returns; and a second run into
a folder another run is writing is refused instead of mixing the two runs' files."""

import os

import pytest

from tests.helpers import SAMPLE_IMAGES, TINY

SLOW_S = 4.0  # how long the program below computes inside XLA

# Run in a process of its own: SIGINT reaches a process's main thread, and a pytest-xdist
# worker runs its tests in another thread.
_PROBE = r"""
import os, signal, sys, threading, time

import jax
import jax.numpy as jnp

from rvggt_jax.app import model_runner, pipeline

SLOW_S = float(sys.argv[1])
# a pytest-xdist worker ignores SIGINT, and a child inherits that: Ctrl-C's Python handler back
signal.signal(signal.SIGINT, signal.default_int_handler)


@jax.jit
def slow(x, n):
    jax.debug.callback(lambda v: None, x[0, 0])
    return jax.lax.fori_loop(0, n, lambda i, y: jnp.sin(y @ y), x)


x = jnp.full((256, 256), 0.01, jnp.float32)
jax.block_until_ready(slow(x, 200))  # compiled
timings = []
for _ in range(3):  # the fastest of three: a busy machine makes the run longer, never shorter
    t0 = time.perf_counter()
    jax.block_until_ready(slow(x, 200))
    timings.append(time.perf_counter() - t0)
steps = int(SLOW_S * 200 / max(min(timings), 1e-6))
if sys.argv[2] == "direct":  # the code before the fix: the forward called in the main thread
    model_runner.interruptible = lambda fn, *a: jax.block_until_ready(fn(*a))
pipeline.run_model = lambda params, images, config, compiled, mesh: slow(x, steps)
threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
t0 = time.perf_counter()
try:
    model_runner.run_model(None, None, None, "tiny")
    print("no interrupt", time.perf_counter() - t0, model_runner.ABANDONED_FORWARD.is_set())
except KeyboardInterrupt:
    print("interrupted", time.perf_counter() - t0, model_runner.ABANDONED_FORWARD.is_set())
sys.stdout.flush()
os._exit(0)  # as `rvggt` does: the abandoned computation is not waited for
"""


def _probe(mode: str) -> tuple[str, float, bool]:
    import subprocess
    import sys

    from tests.helpers import REPO

    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-c", _PROBE, str(SLOW_S), mode], capture_output=True, text=True,
                       timeout=300, cwd=REPO, env=env)
    words = r.stdout.split()
    assert r.returncode == 0 and len(words) >= 3, r.stdout + r.stderr
    return " ".join(words[:-2]), float(words[-2]), words[-1] == "True"


def test_ctrl_c_stops_a_running_forward_promptly():
    """`model_runner.run_model` (what `rvggt reconstruct` runs the forward with) on a
    program that, like the forward, holds a host callback (the input-range check) and then
    computes for seconds: a direct call keeps the main thread inside XLA until the end
    (measured on the tiny model, 24 frames: Ctrl-C arrived after 60 s, when it finished)."""
    what, waited, abandoned = _probe("worker")
    assert what == "interrupted" and waited < SLOW_S / 2, (what, waited)
    assert abandoned  # so `rvggt` leaves at once instead of waiting for it


def test_a_second_run_into_the_same_folder_is_refused(tmp_path):
    from rvggt_jax.app.commands import ReconstructOptions, reconstruct_folder
    from rvggt_jax.app.messages import CLIError
    from rvggt_jax.app.outdir import OutputDirError, output_lock

    out = tmp_path / "out"
    with output_lock(out):
        with pytest.raises(OutputDirError, match=r"another rvggt run \(process \d+\) is writing to"):
            with output_lock(out):
                pass
        with pytest.raises(CLIError, match="another rvggt run"):
            reconstruct_folder(SAMPLE_IMAGES, TINY, out, ReconstructOptions(quiet=True))
    with output_lock(out):  # released when the first run ends
        pass
