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

A flag already in `XLA_FLAGS` wins. `RVGGT_TEST_LLVM_OPT=default` keeps XLA's defaults
(both flags below), for timing a test's program as users compile and run it.
"""

from __future__ import annotations

import os

OPT_FLAG_NAME = "--xla_backend_optimization_level"
# One thread for XLA:CPU's Eigen work in each process: the suite runs 2 xdist workers and
# the sharded worker on 2 cores, and every extra thread only competes with another
# process. Three concurrent compiles of the tiny checkpoint's regime and fastvggt
# forwards took 26.5 s with it against 29.6 s without (and 16.8 against 18.7 CPU s
# each). Runtime threading only: programs, plans and values are the same.
EIGEN_FLAG_NAME = "--xla_cpu_multi_thread_eigen"
SUITE_FLAGS = (f"{OPT_FLAG_NAME}=0", f"{EIGEN_FLAG_NAME}=false")
OPT_OUT_ENV = "RVGGT_TEST_LLVM_OPT"


def suite_flags(flags: str = "") -> str:
    """`flags` (an XLA_FLAGS value) with the suite's flags added: each unless already set;
    none when opted out (RVGGT_TEST_LLVM_OPT=default)."""
    if os.environ.get(OPT_OUT_ENV, "").lower() == "default":
        return flags
    add = [f for f in SUITE_FLAGS if f.split("=")[0] not in flags]
    return " ".join([flags, *add]).strip()
