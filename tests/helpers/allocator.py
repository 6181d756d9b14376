"""The suite's processes run with jemalloc when the machine has it (`LD_PRELOAD`).

Most of the suite's CPU time is XLA compiling small programs, and XLA's compiler (its HLO
passes, MLIR emitters and LLVM) allocates and frees millions of small objects. With glibc's
malloc the tiny checkpoint's dense and `regime` forwards compiled in 11.9-13.9 CPU-s
(-O0, the suite's flags); with jemalloc, in the same runs side by side, 10.2-12.0 (-15%;
the whole process -8 to -10%). tcmalloc did as well; mimalloc (a wheel) and glibc's own
tunables (larger mmap and trim thresholds) gained about half as much. The compiled
programs and their outputs are the same: an allocator decides where blocks live, not what
is computed. Measured in docs/history/suite_time.md (2026-12-07, eleventh session).

The library is the system's (Debian/Ubuntu: `apt-get install libjemalloc2`; `.ci/run`
installs it). Without it, or with `RVGGT_TEST_MALLOC=system`, everything runs on glibc's
malloc as before. The pytest process sets the variable for its children (the xdist
workers, the sharded worker, the `rvggt` subprocesses); it cannot preload into itself,
which only collects and schedules the tests.

The tests of glibc's own malloc settings (tests/app/test_host_heap.py) and the browser of
tests/app/test_viewer.py start their processes without it (`without_preload`).
"""

from __future__ import annotations

import os
from pathlib import Path

OPT_OUT_ENV = "RVGGT_TEST_MALLOC"
# where Debian, Ubuntu and Fedora put the shared library, multiarch folders first
CANDIDATES = tuple(f"{d}/libjemalloc.so.2" for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu",
                                                      "/usr/lib64", "/usr/lib", "/usr/local/lib"))
# set by `preload_jemalloc`: what it added to LD_PRELOAD, so that `without_preload` takes
# out that entry only
ADDED_ENV = "RVGGT_TEST_MALLOC_PRELOADED"


def jemalloc_path() -> str | None:
    """The first of CANDIDATES that exists, or None."""
    return next((c for c in CANDIDATES if Path(c).is_file()), None)


def preload_jemalloc(environ=os.environ) -> str | None:
    """Add jemalloc to `environ`'s LD_PRELOAD (the processes started from now on load it
    first). Returns the library's path, or None when opted out, absent, or already
    preloaded by the caller's environment."""
    if environ.get(OPT_OUT_ENV, "").lower() == "system" or ADDED_ENV in environ:
        return None
    path = jemalloc_path()
    current = environ.get("LD_PRELOAD", "")
    if path is None or "jemalloc" in current or "tcmalloc" in current:
        return None
    environ["LD_PRELOAD"] = f"{path} {current}".strip()
    environ[ADDED_ENV] = path
    return path


def without_preload(environ=os.environ) -> dict[str, str]:
    """A copy of `environ` without the library `preload_jemalloc` added (a process that
    has to run on glibc's malloc)."""
    env = dict(environ)
    added = env.pop(ADDED_ENV, None)
    if added:
        rest = " ".join(p for p in env.get("LD_PRELOAD", "").split() if p != added)
        if rest:
            env["LD_PRELOAD"] = rest
        else:
            env.pop("LD_PRELOAD", None)
    return env
