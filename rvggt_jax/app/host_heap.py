"""The host allocator: freed memory kept for the next run (glibc's malloc, Linux).

XLA:CPU allocates a program's buffers when it runs and frees them when the run ends.
glibc's malloc serves every block above its mmap threshold (128 KiB, rising with use to at
most 32 MiB) with pages mapped for that block alone, and unmaps them when it is freed; the
heap above its trim threshold goes back to the system too. So each run of a compiled
program faults its working set in again, page by page, with the kernel zeroing each one:
a 64-frame `regime` forward of the benchmarks' speed layout takes ~42,000 minor page faults
(~165 MiB) on every run, 2-3% of its time on a 2-core CPU (docs/history/cpu_speed.md, "The host heap").

`keep_freed_host_memory()` sets two of glibc's malloc parameters (`mallopt`):
  - M_MMAP_MAX = 0: no block gets pages of its own; every block comes from the heap;
  - M_TRIM_THRESHOLD at its maximum: freed heap memory stays in the process.
The second run of a program then reuses the pages of the first: no faults, no zeroing.
It changes where buffers live, not what is computed.

The price: the process keeps its peak heap until it exits (freed memory returns to malloc,
not to the system). That suits the `rvggt` command and the benchmarks, which run one model
again and again; a long-lived process that runs the model once and then needs the memory
elsewhere should not call it.

`import rvggt_jax` does not call it. The `rvggt` command calls it first thing, and so do
the benchmarks that time CPU runs. Nothing happens (returns False) on a C library other
than glibc (musl, macOS, Windows) or when `RVGGT_HOST_HEAP=system` (the opt-out). It can be
called at any time; blocks allocated before it keep where they are.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

OPT_OUT_ENV = "RVGGT_HOST_HEAP"
# glibc's mallopt parameter numbers (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
# mallopt takes an int: the largest trim threshold it accepts
TRIM_THRESHOLD_MAX = 2**31 - 1

_applied = False


def _glibc():
    """glibc's handle, or None on another C library."""
    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:  # pragma: no cover - glibc always has it
        return None


def keep_freed_host_memory() -> bool:
    """Make glibc's malloc keep freed memory for reuse (see the module doc). Returns whether
    this process now runs with it (False: not glibc, or opted out with
    `RVGGT_HOST_HEAP=system`)."""
    global _applied
    if os.environ.get(OPT_OUT_ENV, "").lower() == "system":
        return False
    libc = _glibc()
    if libc is None:
        return False
    # mallopt returns 1 on success
    _applied = bool(libc.mallopt(M_MMAP_MAX, 0)) and bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_MAX))
    return _applied


def applied() -> bool:
    """Whether `keep_freed_host_memory` took effect in this process."""
    return _applied


def glibc_environment() -> dict[str, str]:
    """The same two settings as environment variables, which glibc reads when a process
    starts: for a child process that cannot call `keep_freed_host_memory` itself (the
    benchmarks' PyTorch peers run with the same allocator as ours)."""
    return {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_MAX)}
