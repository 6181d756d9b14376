"""The suite's own set-up: its processes run on jemalloc where the machine has it
(tests/helpers/allocator.py), and the processes that must run on glibc's malloc do."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import allocator

MAPS_PROBE = "print(any('libjemalloc' in line for line in open('/proc/self/maps')))"


def _mapped(env) -> str:
    return subprocess.run([sys.executable, "-c", MAPS_PROBE], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


@pytest.mark.skipif(not Path("/proc/self/maps").is_file(), reason="Linux's /proc only")
def test_this_process_and_its_children_have_jemalloc_and_glibc_children_do_not():
    if allocator.jemalloc_path() is None or os.environ.get(allocator.OPT_OUT_ENV, "").lower() == "system":
        pytest.skip("no libjemalloc.so.2 on this machine (apt-get install libjemalloc2), or opted out")
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("the pytest process itself starts without it (only its children preload it)")
    # (an xdist worker: started by the pytest process after conftest set LD_PRELOAD)
    assert any("libjemalloc" in line for line in open("/proc/self/maps"))
    assert _mapped(dict(os.environ)) == "True"
    assert _mapped(allocator.without_preload()) == "False"


def test_preload_adds_one_entry_and_without_preload_takes_out_that_one_only(monkeypatch):
    monkeypatch.setattr(allocator, "jemalloc_path", lambda: "/opt/lib/libjemalloc.so.2")
    env = {"LD_PRELOAD": "/opt/lib/libother.so"}
    assert allocator.preload_jemalloc(env) == "/opt/lib/libjemalloc.so.2"
    assert env["LD_PRELOAD"] == "/opt/lib/libjemalloc.so.2 /opt/lib/libother.so"
    assert allocator.preload_jemalloc(env) is None  # once: a child's conftest adds nothing
    assert env["LD_PRELOAD"].count("jemalloc") == 1
    assert allocator.without_preload(env)["LD_PRELOAD"] == "/opt/lib/libother.so"
    alone = {}
    allocator.preload_jemalloc(alone)
    assert "LD_PRELOAD" not in allocator.without_preload(alone)
    # the user's own allocator, or the opt-out, is left as it is
    for env in ({"LD_PRELOAD": "/usr/lib/libtcmalloc_minimal.so.4"}, {allocator.OPT_OUT_ENV: "system"}):
        before = dict(env)
        assert allocator.preload_jemalloc(env) is None
        assert env == before
    monkeypatch.setattr(allocator, "jemalloc_path", lambda: None)
    env = {}
    assert allocator.preload_jemalloc(env) is None and env == {}
