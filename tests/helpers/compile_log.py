"""Opt-in record of what each test compiles (RVGGT_TEST_COMPILE_LOG=path.jsonl): per test
and phase, the wall time, XLA's compilations (function name, seconds) and the persistent
cache's hits. For keeping the suite's time down: a program compiled by many tests is one
to share (a module fixture, one jitted function). Subprocesses (`rvggt ...`, the sharded
worker) are not recorded."""

from __future__ import annotations

import json
import logging
import os
import re
import time

import jax

_FINISHED = re.compile(r"Finished XLA compilation of (.*) in ([0-9.]+) sec")
_HIT = re.compile(r"Persistent compilation cache hit for '(.*)'")


class CompileLog(logging.Handler):
    def __init__(self, path: str):
        super().__init__(level=logging.DEBUG)
        self.path = path
        self.current: dict | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.current is None:
            return
        msg = record.getMessage()
        if m := _FINISHED.search(msg):
            self.current["compiles"].append([m.group(1), round(float(m.group(2)), 3)])
        elif m := _HIT.search(msg):
            self.current["hits"].append(m.group(1))

    def start(self, nodeid: str, phase: str) -> None:
        self.current = {"test": nodeid, "phase": phase, "worker": os.environ.get("PYTEST_XDIST_WORKER", ""),
                        "compiles": [], "hits": [], "t0": time.perf_counter()}

    def stop(self) -> None:
        if self.current is None:
            return
        rec, self.current = self.current, None
        rec["wall"] = round(time.perf_counter() - rec.pop("t0"), 3)
        rec["compile_s"] = round(sum(s for _, s in rec["compiles"]), 3)
        with open(self.path, "a") as f:
            f.write(json.dumps(rec) + "\n")


def install(path: str) -> CompileLog:
    jax.config.update("jax_log_compiles", True)
    handler = CompileLog(path)
    for name in ("jax._src.interpreters.pxla", "jax._src.compiler", "jax._src.dispatch"):
        logger = logging.getLogger(name)
        logger.addHandler(handler)
        logger.setLevel(logging.DEBUG)
        logger.propagate = False  # (jax_log_compiles' warnings would fill pytest's report)
    return handler
