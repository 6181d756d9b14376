"""XLA flags for every process of the test suite: pytest's, its xdist workers, and the
subprocesses they start (`rvggt ...`, the sharded worker).

`--xla_backend_optimization_level=0` compiles with LLVM at -O0. The suite's time is mostly
XLA compiling small programs, and most of a CPU compile is LLVM optimising machine code
that then runs for milliseconds. The flag applies only after XLA's HLO passes, so fusion,
layouts and buffer assignment are unchanged. On the micro forward the optimised HLO text
and `memory_analysis()` were identical to the default's, and so were the outputs. The
memory plans the tests check are therefore the ones users get.

Measured here, in CPU seconds: compiles take 35-45% less (tiny checkpoint forward 13-14
-> 8-9; micro train step 72-84 -> 43-55). The programs run 1.5-2.5x slower, which is a few
tenths of a second per test at these sizes.

A flag already in `XLA_FLAGS` wins. `RVGGT_TEST_LLVM_OPT=default` keeps XLA's default
level, for timing a test's program as users compile it.
"""

from __future__ import annotations

import os

OPT_FLAG_NAME = "--xla_backend_optimization_level"
SUITE_FLAGS = f"{OPT_FLAG_NAME}=0"
OPT_OUT_ENV = "RVGGT_TEST_LLVM_OPT"


def suite_flags(flags: str = "") -> str:
    """`flags` (an XLA_FLAGS value) with the suite's flags added (unless already set or
    opted out)."""
    if OPT_FLAG_NAME in flags or os.environ.get(OPT_OUT_ENV, "").lower() == "default":
        return flags
    return f"{flags} {SUITE_FLAGS}".strip()
