"""Ctrl-C while the model runs (issue 53): the forward runs in a worker thread, so the
interrupt reaches the command at once instead of when XLA returns; and a second run into
a folder another run is writing is refused instead of mixing the two runs' files."""

import os
import signal
import threading
import time

import pytest

from tests.helpers import DEMO_IMAGES, TINY

SLOW_S = 4.0  # how long the program below computes inside XLA


def test_ctrl_c_stops_a_running_forward_promptly(monkeypatch):
    """`model_runner.run_model` (what `rvggt reconstruct` runs the forward with) on a
    program that, like the forward, holds a host callback (the input-range check) and then
    computes for seconds: a direct call keeps the main thread inside XLA until the end
    (measured on the tiny model, 24 frames: Ctrl-C arrived after 60 s, when it finished)."""
    import jax
    import jax.numpy as jnp

    from rvggt_jax.app import model_runner, pipeline

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
    monkeypatch.setattr(pipeline, "run_model", lambda params, images, config, compiled, mesh: slow(x, steps))
    assert not model_runner.ABANDONED_FORWARD.is_set()
    timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT))
    t0 = time.perf_counter()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            model_runner.run_model(None, None, None, "tiny")
        waited = time.perf_counter() - t0
    finally:
        timer.cancel()
    assert waited < SLOW_S / 2, f"Ctrl-C took {waited:.1f} s to arrive"
    assert model_runner.ABANDONED_FORWARD.is_set()  # so `rvggt` leaves at once instead of waiting for it
    model_runner.ABANDONED_FORWARD.clear()


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
            reconstruct_folder(DEMO_IMAGES, TINY, out, ReconstructOptions(quiet=True))
    with output_lock(out):  # released when the first run ends
        pass
