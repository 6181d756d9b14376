"""`rvggt plan`: the plan against the target's memory, exit 0 when it fits, 3 with what
would fit when it does not, 2 for bad arguments, 1 for missing compilers. Run in-process
(`cli.main`) on the small model of tests/helpers/micro.py (`--config`); the CPU target
with RVGGT_MEMORY_LIMIT_GB makes "does not fit" cheap."""

from __future__ import annotations

import argparse
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
    # 0.79 MiB at 8 frames (0.6 MiB of weights), against a limit of 0.76 MiB: the settings
    # that save memory are compiled together (bf16 + regime: 0.56 MiB), frames are estimated
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "0.0008")
    code, out, err = _plan(capsys, "--frames", "8", *SMALL, "--target", "cpu", "--config", config_json)
    assert code == pc.DOES_NOT_FIT == 3, err
    assert re.search(r"DOES NOT FIT: needs [\d.]+ MiB of 0.76 MiB \(10\d%\), short by", out), out
    assert re.search(r"--dtype bfloat16 --preset regime +planned, fits: 0\.[0-6]\d MiB of 0.76 MiB", out), out
    fit = int(re.search(r"--frames (\d+) +estimate: about [\d.]+ MiB of 0.76 MiB", out).group(1))
    assert 1 <= fit < 8 and f"`rvggt reconstruct` keeps {fit} frames with --max-frames {fit}" in out
    assert "compiling the alternative --dtype bfloat16 --preset regime for cpu" in err


def _bytes(out: str, part: str) -> float:
    value, unit = re.search(rf"{part} +([\d.]+) (GiB|MiB|KiB)", out).groups()
    return float(value) * {"GiB": 2 ** 30, "MiB": 2 ** 20, "KiB": 2 ** 10}[unit]


def test_low_memory_plans_the_low_memory_mode(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "4")
    path = tmp_path / "config.json"
    plan_config("depth").to_json(path)  # (a depth head: its outputs are what the mode halves)
    args = ["--frames", "8", *SMALL, "--target", "cpu", "--config", str(path)]
    code, default, err = _plan(capsys, *args)
    assert code == 0, err
    code, low, err = _plan(capsys, *args, "--low-memory")
    assert code == 0, err
    assert "low-memory mode" in low and "low-memory mode" not in default
    # float16 / bfloat16 outputs: half the bytes of the dense outputs (the pose stays float32)
    assert _bytes(low, "outputs") < 0.6 * _bytes(default, "outputs"), (low, default)


def _report(**kw) -> MemoryReport:
    base = dict(frames=1000, height=392, width=518, batch=1, dtype="bfloat16", param_dtype="bfloat16",
                preset="regime", argument_bytes=None, output_bytes=None, temp_bytes=None, alias_bytes=None,
                compile_seconds=1.0, target="tpu-v6e", memory_bytes=32 * 2 ** 30, needed_bytes=80 * 2 ** 30)
    return MemoryReport(**{**base, **kw})


def test_suggested_frames_and_devices_follow_the_linear_estimate():
    gib = 2 ** 30
    # 80 GiB of which 2 GiB of weights on a 32 GiB TPU: 78 GiB for 1000 frames
    tips = {t.options: t for t in pc.scaling(_report(), tg.TARGETS["tpu-v6e"], 2 * gib, {})}
    budget = 0.95 * 32 * gib - 2 * gib
    fit = int(1000 * budget / (78 * gib))
    assert list(tips) == [f"--frames {fit}", "--devices 4"]  # 78 / 28.4 -> 3 devices, a TPU slice of 4
    assert tips[f"--frames {fit}"].label == f"estimate: about {pc.fmt_bytes(int(2 * gib + 78 * gib * fit / 1000))}" \
                                           " of 32.00 GiB (95%)"
    both = pc.scaling(_report(target="h100"), tg.TARGETS["h100"], 2 * gib, {"dtype": "bfloat16"})
    assert [t.options for t in both] == [f"--dtype bfloat16 --frames {int(1000 * (0.95 * 32 * gib - 2 * gib) / (78 * gib))}",
                                         "--dtype bfloat16 --devices 3"]
    heavy = pc.scaling(_report(), tg.TARGETS["tpu-v6e"], 40 * gib, {})
    assert [(t.options, t.changes) for t in heavy] == [("a larger target", {})]
    # 1000 frames at 80 GiB, but one frame at 1000 x the pixels: not even one fits
    huge = pc.scaling(_report(frames=1, needed_bytes=80 * gib), tg.TARGETS["cpu"], 2 * gib, {})
    assert [t.options for t in huge] == ["smaller images or a larger target"]
    settings = {"dtype": "float32", "param_dtype": None, "preset": "dense"}
    assert pc.setting_changes(argparse.Namespace(**settings)) == {"dtype": "bfloat16", "preset": "regime"}
    assert pc.setting_changes(argparse.Namespace(**{**settings, "dtype": "bfloat16", "param_dtype": "float32",
                                                    "preset": "regime"})) == {"param_dtype": "bfloat16"}


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
    # float32 images, donated: the point map written into their buffer (docs/accelerators.md)
    donated = "\n".join(pc._describe(dataclasses.replace(rep, image_dtype="float32", alias_bytes=2 * mib),
                                     tg.TARGETS["tpu-v6e"], "VGGT-1B"))
    assert "aliased      -2.00 MiB (outputs written into the donated images' buffer)" in donated
    assert "total        13.00 MiB" in donated
    refused = "\n".join(pc._describe(_report(memory_what="TPU v6e"), tg.TARGETS["tpu-v6e"], "VGGT-1B"))
    assert "n/a (XLA refused the program" in refused and "total        80.00 GiB of 32.00 GiB" in refused


def test_a_triton_gemm_xla_cannot_tile_without_the_device_is_planned_with_cublas(capsys, monkeypatch, tmp_path):
    # the DPT head's small float32 gemm that XLA:GPU cannot tile for an H100 without the
    # device ("Couldn't find output tile sizes"): planned again without Triton gemms, as
    # the Ampere targets always are, and the plan says so
    path = tmp_path / "depth.json"
    plan_config("depth").to_json(path)
    code, out, err = _plan(capsys, "--frames", "1", "--height", "14", "--width", "14", "--target", "h100",
                           "--config", str(path))
    assert code == 0, err
    assert "fallback     xla_gpu_enable_triton_gemm=false: XLA:GPU could not tile a Triton gemm" in out, out
    assert "FITS:" in out and "compiling again with xla_gpu_enable_triton_gemm=false" in err


def _fake_planner(monkeypatch, sizes: dict, peak_share: float = 1.0, delay: float = 0.0) -> list:
    """`memory_report` replaced by chosen figures: sizes[(dtype, preset)] GiB at 1000 frames
    on one device, linear in the frames, split over the devices. A TPU compiles what has a
    peak (total x peak_share) within its HBM and refuses the rest. Returns the calls as
    (dtype, preset, frames, devices, total bytes)."""
    import time

    calls = []

    def fake(config, frames, height, width, *, batch, param_dtype, target, devices, image_dtype, progress=None):
        time.sleep(delay)
        t = tg.get_target(target)
        total = int(sizes[config.dtype, config.compression.name] * 2 ** 30 * frames / 1000 / devices)
        calls.append((config.dtype, config.compression.name, frames, devices, total))
        rep = _report(frames=frames, dtype=config.dtype, param_dtype=param_dtype, preset=config.compression.name,
                      target=t.name, memory_bytes=t.memory_bytes, memory_what=t.title, devices=devices,
                      needed_bytes=None, argument_bytes=0, output_bytes=0, temp_bytes=total, alias_bytes=0,
                      device_kind="fake", attention="blocked")
        if t.platform != "tpu":
            return rep
        if total * peak_share > t.memory_bytes:
            return dataclasses.replace(rep, needed_bytes=total, temp_bytes=None, output_bytes=None,
                                       argument_bytes=None, alias_bytes=None)
        return dataclasses.replace(rep, compiler_checked=True, peak_bytes=int(total * peak_share))

    monkeypatch.setattr("rvggt_jax.planning.memory.memory_report", fake)
    return calls


def _alternatives(out: str) -> list[tuple[str, str]]:
    """(options, label; why) of each alternative printed: the indented lines that end the output."""
    lines = out.rstrip("\n").splitlines()
    start = max(i for i, line in enumerate(lines) if not line.startswith(" ")) + 1
    return [re.match(r" {2}(\S.*?) {2,}(\S.*)$", row).groups() for row in lines[start:]]


@pytest.mark.parametrize("target, sizes", [
    ("rtx4090", {("float32", "dense"): 80, ("bfloat16", "regime"): 34.29}),
    ("tpu-v5e", {("float32", "dense"): 72.5, ("bfloat16", "regime"): 20}),
])
@pytest.mark.parametrize("check", [False, True])
def test_an_alternative_fits_only_when_compiled_and_its_options_are_plans(capsys, monkeypatch, config_json,
                                                                          target, sizes, check):
    calls = _fake_planner(monkeypatch, sizes)
    flags = ["--check-suggestions"] if check else []
    code, out, err = _plan(capsys, "--frames", "1000", "--target", target, "--config", config_json, *flags)
    assert code == pc.DOES_NOT_FIT, err
    tips = _alternatives(out)
    for options, _ in tips:  # every option is one of `rvggt plan`'s own (no --max-frames)
        if options.startswith("--"):
            cli.build_parser().parse_args(["plan", "--frames", "1000", "--target", target, *options.split()])
    have = tg.TARGETS[target].memory_bytes
    combined = f"planned, does not fit: needs {sizes['bfloat16', 'regime']:.2f} GiB of {pc.fmt_bytes(have)}"
    assert tips[0][0] == "--dtype bfloat16 --preset regime" and tips[0][1].startswith(combined), tips
    # the calls in order: the plan, then each alternative compiled
    compiled = {options: total for options, (*_, total) in
                zip(["the plan", *(o for o, _ in tips if o.startswith("--"))], calls)}
    assert len(calls) == (1 + sum(o.startswith("--") for o, _ in tips) if check else 2)  # bounded
    for options, said in tips:
        if not options.startswith("--"):
            continue
        assert said.startswith("planned, " if check else ("planned, ", "estimate: about ")), said
        if said.startswith("planned, fits"):  # compiled, and it fit
            assert options in compiled and compiled[options] <= have, (options, said)
        elif not said.startswith("planned, does not fit"):
            assert "fits" not in said and re.match(r"estimate: about [\d.]+ GiB of", said), said
    assert any(s.startswith("planned, fits") for _, s in tips) == check  # the estimates hit 95%


def test_progress_while_compiling_and_one_verdict_without_a_share_over_100_percent(capsys, monkeypatch,
                                                                                  config_json):
    # a TPU plan whose memory analysis sums to 33.71 GiB of 31.25 GiB, compiled by XLA:TPU
    # (a peak of 22 GiB): it fits, and the verdict says by which of XLA's numbers
    monkeypatch.setattr(pc, "PROGRESS_EVERY", 0.02, raising=False)
    _fake_planner(monkeypatch, {("float32", "dense"): 33.71}, peak_share=22 / 33.71, delay=0.1)
    code, out, err = _plan(capsys, "--frames", "1000", "--target", "tpu-v6e", "--config", config_json)
    assert code == 0, err
    assert re.search(r"compiling the forward for tpu-v6e \(libtpu's v6e; .*\) \.\.\.\n(  \.\.\. still compiling the "
                     r"forward \(0\.\d s\)\n)+  compiled in 0\.\d s", err), err
    verdicts = [line for line in out.splitlines() if re.match(r"(FITS|DOES NOT FIT)\b", line)]
    assert verdicts == ["FITS: compiled for the 31.25 GiB of HBM, heap-simulation peak 22.00 GiB (70%) "
                        "(XLA:TPU's own HBM check decides, not the total)."], out
    assert all(int(p) <= 100 for p in re.findall(r"(\d+)%", out)), out
    assert "total        33.71 GiB: the sum above, an upper bound, not the verdict" in out


@pytest.mark.parametrize("kw, expected", [
    (dict(), "DOES NOT FIT: needs 80.00 GiB of 32.00 GiB (250%) (XLA:TPU refused to compile it: its own HBM check "
             "decides)."),
    (dict(needed_bytes=None, argument_bytes=0, output_bytes=0, temp_bytes=40 * 2 ** 30, alias_bytes=0,
          compiler_checked=True, peak_bytes=40 * 2 ** 30),
     "FITS: compiled for the 32.00 GiB of HBM (XLA:TPU's own HBM check decides, not the total)."),
    (dict(needed_bytes=None, argument_bytes=0, output_bytes=0, temp_bytes=24 * 2 ** 30, alias_bytes=0,
          target="h100"), "FITS: 24.00 GiB of 32.00 GiB (75%), 8.00 GiB to spare (XLA's planned total decides)."),
    (dict(needed_bytes=None, argument_bytes=0, output_bytes=0, temp_bytes=40 * 2 ** 30, alias_bytes=0,
          target="h100"), "DOES NOT FIT: needs 40.00 GiB of 32.00 GiB (125%), short by 8.00 GiB (XLA's planned "
                          "total decides)."),
])
def test_the_verdict_names_the_number_that_decides(kw, expected):
    assert pc.verdict(_report(**kw)) == expected
