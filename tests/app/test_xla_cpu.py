"""`rvggt_jax.prefer_threaded_convolutions()` routes CPU convolutions to XLA's
multi-threaded path (`rvggt_jax.app.xla_cpu`), only when it safely can; the `rvggt`
command calls it, `import rvggt_jax` alone does not. Each case runs in a fresh
interpreter: XLA reads its flags once."""

from __future__ import annotations

import os
import subprocess
import sys
import pytest

from rvggt_jax.app import xla_cpu
from tests.helpers.paths import REPO as ROOT

PROBE = """
import {first}
import contextlib, io
import jax, jax.numpy as jnp
import rvggt_jax
from rvggt_jax.app import xla_cpu
{call}
x = jnp.zeros((2, 48, 64, 64)); k = jnp.zeros((3, 3, 64, 64))
conv = jax.jit(lambda x: jax.lax.conv_general_dilated(x, k, (1, 1), "SAME",
                                                       dimension_numbers=("NHWC", "HWIO", "NHWC")))
hlo = conv.lower(x).compile().as_text()
print(xla_cpu.applied(), "ynn" in hlo.lower())
"""


CALL = "rvggt_jax.prefer_threaded_convolutions()"
# the `rvggt` entry point with no command (prints its help, returns 2; its stdout is dropped)
CLI_MAIN = ("from rvggt_jax.app.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n    assert main([]) == 2")


def _probe(first: str = "os", call: str = CALL, **env) -> tuple[str, str]:
    full_env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", xla_cpu.OPT_OUT_ENV)}
    full_env.update(env)
    full_env["PYTHONPATH"] = str(ROOT)
    if first == "started":  # a backend already running before rvggt_jax is imported
        first = "jax; jax.numpy.ones(1)"
    out = subprocess.run([sys.executable, "-c", PROBE.format(first=first, call=call)], env=full_env, cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.split()
    return out[0], out[1]


pytestmark = pytest.mark.skipif(xla_cpu._jaxlib_version() not in xla_cpu.VERIFIED_JAXLIB,
                                reason="flag only applied on verified jaxlib versions")


def test_call_moves_convolutions_off_single_threaded_ynnpack():
    assert _probe() == ("True", "False")


def test_import_alone_keeps_xla_default():
    assert _probe(call="") == ("False", "True")


def test_cli_main_applies_it():
    assert _probe(call=CLI_MAIN) == ("True", "False")
    assert _probe(call=CLI_MAIN, **{xla_cpu.OPT_OUT_ENV: "ynn"}) == ("False", "True")


def test_opt_out_keeps_xla_default():
    assert _probe(**{xla_cpu.OPT_OUT_ENV: "ynn"}) == ("False", "True")


def test_users_own_flag_wins():
    assert _probe(XLA_FLAGS="--xla_cpu_experimental_ynn_fusion_type=individual_convolution") == ("False", "True")


def test_no_effect_once_a_backend_runs():
    assert _probe(first="started") == ("False", "True")


CPU_PROBE = """
import os, sys
from rvggt_jax.app import xla_cpu
import jax
set_it = xla_cpu.use_cpu_without_accelerator(tuple(sys.argv[1:]))
print(set_it, os.environ.get("JAX_PLATFORMS"), jax.devices()[0].platform)
"""


@pytest.mark.parametrize("case", ["no accelerator", "accelerator node", "user's choice"])
def test_cpu_backend_on_a_host_without_accelerators(tmp_path, case):
    """`use_cpu_without_accelerator` (the `rvggt` command calls it first): on a host without
    a GPU's or TPU's device node JAX runs on its CPU backend without initialising the
    installed accelerator plugins (the `[plan]` extra's CUDA and TPU plugins print
    tracebacks when their device is absent); with a device node, or JAX_PLATFORMS set by
    the user, nothing changes. Fresh interpreters: JAX reads the setting once."""
    node = tmp_path / "nvidiactl"
    node.write_text("")
    nodes = {"no accelerator": [str(tmp_path / "absent")], "accelerator node": [str(node)],
             "user's choice": [str(tmp_path / "absent")]}[case]
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    env["PYTHONPATH"] = str(ROOT)
    if case == "user's choice":
        env["JAX_PLATFORMS"] = "cpu"
    r = subprocess.run([sys.executable, "-c", CPU_PROBE, *nodes], capture_output=True, text=True, env=env,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    got = r.stdout.split()
    if case == "no accelerator":
        assert got == ["True", "cpu", "cpu"]
        assert "Traceback" not in r.stderr, r.stderr[-3000:]
    elif case == "accelerator node":
        assert got[:2] == ["False", "None"]
    else:
        assert got == ["False", "cpu", "cpu"]


PLUGIN_PROBE = """
import os, sys
from rvggt_jax.app import xla_cpu
for platforms in sys.argv[1:]:
    os.environ["JAX_PLATFORMS"] = platforms
    print(xla_cpu.leave_cuda_plugin_unloaded(), "jax_cuda12_plugin" in sys.modules)
import jax
print(xla_cpu.leave_cuda_plugin_unloaded())
"""


def test_cuda_plugin_left_unloaded_only_on_the_cpu_alone():
    """`leave_cuda_plugin_unloaded` (the `rvggt` command but `plan` calls it): nothing while
    JAX_PLATFORMS names another platform, the plugin blocked when it names only the CPU,
    and nothing once JAX is imported (the plugin's libraries are loaded by then)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    env["PYTHONPATH"] = str(ROOT)
    r = subprocess.run([sys.executable, "-c", PLUGIN_PROBE, "", "cuda", "cpu,cuda", " CPU "], capture_output=True,
                       text=True, env=env, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split("\n")[:5] == ["False False", "False False", "False False", "True True", "False"]
    assert r.stderr == ""  # JAX imported without the plugin's "Could not find cuda drivers" lines
