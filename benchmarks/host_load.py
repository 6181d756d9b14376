"""How busy the host was with other work while a benchmark timed something.

This machine is shared: another process can take a core for minutes, and a 2-core run
timed then says more about that process than about the code. `bench_peers.py` records,
around every timed call, the CPU time the whole (virtual) machine spent (Linux
`/proc/stat`, steal time included: the hypervisor giving our cores to another guest) and
the CPU time of the process running the call (this one for ours, the peer's worker for
a peer's). What is left, divided by the wall time, is the number of cores other
processes held meanwhile: 0 on a quiet machine, 1 when something else kept one core busy
the whole time. The other side of a comparison counts as "other" too: a peer's threads
still spinning while ours run, or ours while the peer runs, are load on the call timed.

What this cannot see: a neighbour outside the virtual machine that shares its physical
cores, cache or memory slows the same instructions without taking CPU time from it
(docs/benchmarks.md, "Noise this machine cannot see"). Resolution: the kernel counts in
clock ticks (10 ms), so a 0.2 s call reads to about +-0.1 core. Where `/proc/stat` does
not exist (not Linux), `others` is None.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import NamedTuple

PROC_STAT = Path("/proc/stat")
# /proc/stat's "cpu" line: user nice system idle iowait irq softirq steal guest guest_nice.
# Busy is everything but idle and iowait; guest time is already inside user and nice.
_BUSY_FIELDS = (0, 1, 2, 5, 6, 7)


def _ticks_per_second() -> int:
    return os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def host_busy_seconds(stat_text: str | None = None) -> float | None:
    """CPU seconds the whole host has been busy since boot (all cores), from the text of
    /proc/stat (read when not given); None without it."""
    if stat_text is None:
        if not PROC_STAT.exists():
            return None
        stat_text = PROC_STAT.read_text()
    line = stat_text.splitlines()[0] if stat_text.strip() else ""
    first = line.split()
    if not first or first[0] != "cpu":
        raise ValueError(f"/proc/stat's first line is not the all-CPU total: {line!r}")
    fields = [int(v) for v in first[1:]]
    return sum(fields[i] for i in _BUSY_FIELDS if i < len(fields)) / _ticks_per_second()


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` (all its threads), from /proc/<pid>/stat."""
    text = Path(f"/proc/{pid}/stat").read_text()
    # fields after the command name (which may hold spaces, inside parentheses)
    fields = text[text.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / _ticks_per_second()


class Snapshot(NamedTuple):
    wall: float  # time.perf_counter()
    host: float | None  # host_busy_seconds()
    measured: float  # CPU seconds of the processes being measured


def snapshot(pids: tuple[int, ...] = (), own: bool = True) -> Snapshot:
    """Now: wall clock, host busy CPU seconds, and the CPU seconds of the processes being
    timed: this one (all its threads) unless `own` is False, plus the processes `pids`."""
    measured = time.process_time() if own else 0.0
    if PROC_STAT.exists():
        measured += sum(process_cpu_seconds(pid) for pid in pids)
    return Snapshot(time.perf_counter(), host_busy_seconds(), measured)


def others(before: Snapshot, after: Snapshot) -> float | None:
    """Cores held by processes other than the measured ones between two snapshots (>= 0;
    tick rounding can make a quiet host read slightly negative, clipped to 0)."""
    if before.host is None or after.host is None:
        return None
    wall = after.wall - before.wall
    if wall <= 0:
        raise ValueError("the second snapshot must be taken after the first")
    return max(0.0, ((after.host - before.host) - (after.measured - before.measured)) / wall)

