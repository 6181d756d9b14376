"""benchmarks/host_load.py: the cores other processes held while a benchmark timed a call
(bench_peers.py prints it for every round)."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from benchmarks import host_load
from benchmarks.host_load import Snapshot

TICK = host_load._ticks_per_second()


def test_busy_seconds_are_every_field_but_idle_and_iowait():
    #            user nice system idle iowait irq softirq steal guest guest_nice
    text = "cpu  100 20 30 1000 50 5 6 10 7 0\ncpu0 50 10 15 500 25 2 3 5 0 0\n"
    assert host_load.host_busy_seconds(text) == pytest.approx((100 + 20 + 30 + 5 + 6 + 10) / TICK)


def test_a_stat_text_without_the_total_line_is_refused():
    for text in ("cpu0 1 2 3 4\n", ""):
        with pytest.raises(ValueError, match="all-CPU total"):
            host_load.host_busy_seconds(text)


def test_others_are_the_host_busy_time_not_measured_per_wall_second():
    assert host_load.others(Snapshot(0.0, 10.0, 5.0), Snapshot(2.0, 13.0, 6.0)) == pytest.approx(1.0)
    # tick rounding can read a quiet host below zero
    assert host_load.others(Snapshot(0.0, 10.0, 5.0), Snapshot(1.0, 10.99, 6.0)) == 0.0
    assert host_load.others(Snapshot(0.0, None, 5.0), Snapshot(1.0, 11.0, 6.0)) is None
    with pytest.raises(ValueError, match="after the first"):
        host_load.others(Snapshot(1.0, 10.0, 5.0), Snapshot(1.0, 11.0, 6.0))


@pytest.mark.skipif(not host_load.PROC_STAT.exists(), reason="needs Linux /proc")
def test_a_busy_child_counts_as_others_until_it_is_measured():
    """A child spinning for 2 s, watched for 1 s: unmeasured, its core is others' load;
    measured (its pid given), it is not. Both from the same interval, so whatever else the
    host runs cancels out of the difference."""
    child = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 2: pass"])
    try:
        time.sleep(0.2)  # started and spinning
        before = (host_load.snapshot(), host_load.snapshot((child.pid,)))
        time.sleep(1.0)
        after = (host_load.snapshot(), host_load.snapshot((child.pid,)))
        unmeasured = host_load.others(before[0], after[0])
        measured = host_load.others(before[1], after[1])
    finally:
        child.wait()
    # the child had at least a fifth of a core even on a host running the whole suite
    assert unmeasured >= 0.2
    assert unmeasured - measured >= 0.2


@pytest.mark.skipif(not host_load.PROC_STAT.exists(), reason="needs Linux /proc")
def test_this_process_is_others_when_not_measured():
    """bench_peers times a peer with only the peer measured: our own process spinning
    meanwhile is load on that call."""
    before = (host_load.snapshot(own=True), host_load.snapshot(own=False))
    t = time.perf_counter()
    while time.perf_counter() - t < 0.6:
        pass
    after = (host_load.snapshot(own=True), host_load.snapshot(own=False))
    assert host_load.others(before[1], after[1]) - host_load.others(before[0], after[0]) >= 0.2
