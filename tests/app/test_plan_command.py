"""`rvggt plan`: the plan against the target's memory, exit 0 when it fits, 3 with what
would fit when it does not, 2 for bad arguments, 1 for missing compilers. Run in-process
(`cli.main`) on the small model of tests/helpers/micro.py (`--config`); the CPU target
with RVGGT_MEMORY_LIMIT_GB makes "does not fit" cheap."""

from __future__ import annotations

import dataclasses
import os
import re
import sys

import pytest

from rvggt_jax.app import cli
from rvggt_jax.app import plan_command as pc
from rvggt_jax.planning import targets as tg
from rvggt_jax.planning.memory import MEMORY_LIMIT_ENV, MemoryReport
from tests.helpers.micro import plan_config

SMALL = ["--height", "28", "--width", "42"]


@pytest.fixture(scope="module")
def config_json(tmp_path_factory):
    path = tmp_path_factory.mktemp("plan") / "config.json"
    plan_config().to_json(path)
    return str(path)


def _plan(capsys, *args: str) -> tuple[int, str, str]:
    code = cli.main(["plan", *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_a_plan_that_fits_exits_0(capsys, config_json, monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "4")
    # (the program of the next test: compiled once in this process)
    code, out, err = _plan(capsys, "--frames", "8", *SMALL, "--target", "cpu", "--config", config_json)
    assert code == 0, err
    for part in ("8 frames of 28 x 42", "preset dense", "attention    blocked", "arguments", "outputs",
                 "temporaries", "total", "of 3.73 GiB", "FITS:"):
        assert part in out, (part, out)


def test_a_plan_that_does_not_fit_exits_3_saying_what_would(capsys, config_json, monkeypatch):
    # 0.93 MB at 8 frames (0.6 MB of weights), against a limit of 0.8 MB; --verify compiles
    # the suggested frame count
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "0.0008")
    code, out, err = _plan(capsys, "--frames", "8", *SMALL, "--target", "cpu", "--config", config_json, "--verify")
    assert code == pc.DOES_NOT_FIT == 3, err
    assert "DOES NOT FIT: needs" in out and "short by" in out
    assert "--dtype bfloat16" in out and "--preset regime" in out
    fit = int(re.search(r"--max-frames (\d+)", out).group(1))
    assert 1 <= fit < 8
    assert re.search(rf"checked: {fit} frames need [\d.]+ MiB: fits", out), out


def _report(**kw) -> MemoryReport:
    base = dict(frames=1000, height=392, width=518, batch=1, dtype="bfloat16", param_dtype="bfloat16",
                preset="regime", argument_bytes=None, output_bytes=None, temp_bytes=None, alias_bytes=None,
                compile_seconds=1.0, target="tpu-v6e", memory_bytes=32 * 2 ** 30, needed_bytes=80 * 2 ** 30)
    return MemoryReport(**{**base, **kw})


def test_suggested_frames_and_devices_follow_the_linear_estimate():
    gib = 2 ** 30
    # 80 GiB of which 2 GiB of weights on a 32 GiB TPU: 78 GiB for 1000 frames
    tips = dict(pc.suggestions(_report(), tg.TARGETS["tpu-v6e"], params=2 * gib))
    budget = 0.95 * 32 * gib - 2 * gib
    assert f"--max-frames {int(1000 * budget / (78 * gib))}" in tips
    assert "--devices 4" in tips  # 78 / 28.4 -> 3 devices, a TPU slice of 4
    assert "--dtype bfloat16" not in tips and "--preset regime" not in tips  # already
    gpu = dict(pc.suggestions(_report(target="h100", dtype="float32", param_dtype="float32", preset="dense"),
                              tg.TARGETS["h100"], params=2 * gib))
    assert "--dtype bfloat16" in gpu and "--preset regime" in gpu and "--devices 3" in gpu
    heavy = dict(pc.suggestions(_report(param_dtype="float32"), tg.TARGETS["tpu-v6e"], params=40 * gib))
    assert list(heavy) == ["--param-dtype bfloat16", "a larger target"]
    # 1000 frames at 80 GiB, but one frame at 1000 x the pixels: not even one fits
    huge = dict(pc.suggestions(_report(frames=1, needed_bytes=80 * gib), tg.TARGETS["cpu"], params=2 * gib))
    assert list(huge) == ["smaller images or a larger target"]


def test_a_gpu_plan_above_jaxs_default_share_says_which_fraction_to_run_with():
    gib = 2 ** 30
    h200 = tg.TARGETS["h200"]
    fits = dict(needed_bytes=None, argument_bytes=10 * gib, output_bytes=10 * gib, alias_bytes=0, target="h200",
                memory_bytes=h200.memory_bytes)
    assert pc.memory_fraction_note(_report(**fits, temp_bytes=80 * gib), h200) is None  # 71%
    note = pc.memory_fraction_note(_report(**fits, temp_bytes=105 * gib), h200)  # 88.7%
    assert "XLA_PYTHON_CLIENT_MEM_FRACTION=0.91" in note
    assert pc.memory_fraction_note(_report(**fits, temp_bytes=105 * gib), tg.TARGETS["tpu-v6e"]) is None


@pytest.mark.parametrize("args, message", [
    (["--frames", "4", "--target", "h300"], "unknown target 'h300'; choose one of: h100, h200, a100-40gb"),
    (["--frames", "4", "--target", "h200", "--height", "30"], "--height must be a positive multiple of the patch"),
    (["--frames", "4", "--target", "h200", "--attention", "cudnn"], "takes bfloat16 only"),
    (["--frames", "4", "--target", "h200", "--preset", "fast"], "unknown preset 'fast'; known presets: dense"),
    (["--frames", "0", "--target", "h200"], "--frames must be at least 1"),
    (["--frames", "4", "--target", "tpu-v6e", "--devices", "3"], "power of two"),
    (["--frames", "4", "--target", "h200", "--dtype", "float16"], "invalid choice"),
    (["--target", "h200"], "--frames"),
])
def test_bad_arguments_exit_2_with_one_line(capsys, args, message):
    code, out, err = _plan(capsys, *args)  # each refused before anything compiles
    assert code == 2, (out, err)
    assert err.startswith("rvggt: error: ") and message in err, err


def test_missing_compilers_exit_1_saying_what_to_install(capsys, monkeypatch, config_json):
    monkeypatch.setitem(sys.modules, "libtpu", None)
    code, out, err = _plan(capsys, "--frames", "2", *SMALL, "--target", "tpu-v6e", "--config", config_json)
    assert code == 1 and 'pip install "rvggt-jax[plan]"' in err, err


def test_plan_runs_jax_on_the_cpu_unless_told_otherwise(monkeypatch):
    import jax

    updates = []
    monkeypatch.setattr(jax.config, "update", lambda name, value: updates.append((name, value)))
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    pc.use_host_compilers()
    assert os.environ["JAX_PLATFORMS"] == "cpu" and updates == [("jax_platforms", "cpu")]
    monkeypatch.setenv("JAX_PLATFORMS", "cuda")  # the user's choice stays
    pc.use_host_compilers()
    assert os.environ["JAX_PLATFORMS"] == "cuda" and len(updates) == 1


def test_help_names_the_targets(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["plan", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert all(name in out for name in tg.TARGETS) and "exit status" in out.lower()


def test_the_printed_plan_names_its_parts_and_the_target():
    mib = 2 ** 20
    rep = dataclasses.replace(_report(), needed_bytes=None, image_dtype="uint8", argument_bytes=3 * mib, output_bytes=2 * mib,
                              temp_bytes=10 * mib, alias_bytes=0, memory_bytes=20 * mib, memory_what="TPU v6e",
                              device_kind="TPU v6 lite", attention="tpu_flash")
    lines = "\n".join(pc._describe(rep, tg.TARGETS["tpu-v6e"], "VGGT-1B"))
    assert "VGGT-1B, 1 x 1000 frames of 392 x 518 (uint8), preset regime, bfloat16 (weights bfloat16)" in lines
    assert "temporaries  10.00 MiB" in lines and "total        15.00 MiB of 20.00 MiB (75%): TPU v6e" in lines
    assert "libtpu's v6e (TPU v6 lite)" in lines and "attention    tpu_flash" in lines
    assert "peak" not in lines and "upper bound" not in lines
    compiled = "\n".join(pc._describe(dataclasses.replace(rep, peak_bytes=12 * mib, compiler_checked=True),
                                      tg.TARGETS["tpu-v6e"], "VGGT-1B"))
    assert "peak         12.00 MiB (XLA's heap simulation" in compiled and "an upper bound" in compiled
    refused = "\n".join(pc._describe(_report(memory_what="TPU v6e"), tg.TARGETS["tpu-v6e"], "VGGT-1B"))
    assert "n/a (XLA refused the program" in refused and "total        80.00 GiB of 32.00 GiB" in refused
