"""`rvggt plan --memory-gb G`: the plan held against G GiB instead of the target's memory,
the verdict and the exit status by G; bad values exit 2. The reports are made by hand (no
compile): `judge` / `verdict` of `held_against`, and the command with a stand-in planner."""

from __future__ import annotations

import dataclasses

import pytest

from rvggt_jax.app import cli
from rvggt_jax.app import plan_command as pc
from rvggt_jax.planning import targets as tg
from rvggt_jax.planning.memory import MemoryReport
from tests.helpers.micro import plan_config

GiB = 2 ** 30


def _report(target: str, **kw) -> MemoryReport:
    base = dict(frames=100, height=392, width=518, batch=1, dtype="bfloat16", param_dtype="bfloat16", preset="regime",
                argument_bytes=2 * GiB, output_bytes=GiB, temp_bytes=17 * GiB, alias_bytes=0, compile_seconds=1.0,
                target=target, memory_bytes=tg.TARGETS[target].memory_bytes, memory_what=tg.TARGETS[target].title)
    return MemoryReport(**{**base, **kw})


def test_a_gpu_plan_is_held_against_g():
    rep = _report("h100")  # 20 GiB of the H100's 79.11
    assert pc.fits(rep) and pc.fits(pc.held_against(rep, None)) and pc.held_against(rep, None) is rep
    small = pc.held_against(rep, 16)
    assert small.memory_bytes == 16 * GiB and "--memory-gb 16, instead of 79.11 GiB" in small.memory_what
    assert pc.verdict(small) == ("DOES NOT FIT: needs 20.00 GiB of 16.00 GiB (125%), short by 4.00 GiB (XLA's "
                                 "planned total decides).")
    assert pc.verdict(pc.held_against(rep, 24)) == ("FITS: 20.00 GiB of 24.00 GiB (83%), 4.00 GiB to spare (XLA's "
                                                    "planned total decides).")


def test_a_tpu_plan_below_the_chips_hbm_is_judged_by_its_heap_simulation_peak():
    # compiled for the v6e's 31.25 GiB; its parts sum to 40 GiB (an upper bound), the peak 12 GiB
    rep = _report("tpu-v6e", temp_bytes=37 * GiB, compiler_checked=True, peak_bytes=12 * GiB)
    assert pc.verdict(pc.held_against(rep, 16)) == ("FITS: 12.00 GiB of 16.00 GiB (75%), 4.00 GiB to spare "
                                                    "(XLA:TPU's heap-simulation peak decides).")
    assert pc.verdict(pc.held_against(rep, 8)) == ("DOES NOT FIT: needs 12.00 GiB of 8.00 GiB (150%), short by "
                                                   "4.00 GiB (XLA:TPU's heap-simulation peak decides).")
    assert not pc.fits(pc.held_against(dataclasses.replace(rep, peak_bytes=None), 32 - 1))  # the total, 40 GiB
    assert pc.verdict(pc.held_against(rep, 64)).startswith("FITS: compiled for the chip's 31.25 GiB of HBM, within "
                                                           "the 64.00 GiB held against")
    # refused by XLA:TPU at 80 GiB: fits 100 GiB, not 64
    refused = _report("tpu-v6e", argument_bytes=None, output_bytes=None, temp_bytes=None, alias_bytes=None,
                      needed_bytes=80 * GiB)
    assert pc.fits(pc.held_against(refused, 100)) and not pc.fits(pc.held_against(refused, 64))
    assert not pc.fits(refused)


@pytest.mark.parametrize("value", ["0", "-3", "nan", "inf"])
def test_a_bad_memory_gb_exits_2_before_anything_compiles(capsys, value):
    code = cli.main(["plan", "--frames", "4", "--target", "h100", "--memory-gb", value])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("rvggt: error: --memory-gb must be a positive number of GiB; got "), err


def test_the_exit_status_follows_g(capsys, monkeypatch, tmp_path):
    """The command with a stand-in planner: 20 GiB on an H100 fits its 79 GiB and 24 GiB,
    not 16 GiB (exit 3, alternatives held against 16 GiB too)."""
    config = tmp_path / "config.json"
    plan_config().to_json(config)

    def planner(cfg, frames, height, width, *, batch, param_dtype, target, devices, image_dtype, progress=None):
        return _report("h100", frames=frames, dtype=cfg.dtype, preset=cfg.compression.name, devices=devices,
                       device_kind="fake", attention="cudnn")

    monkeypatch.setattr("rvggt_jax.planning.memory.memory_report", planner)
    args = ["plan", "--frames", "100", "--height", "28", "--width", "42", "--target", "h100", "--config", str(config)]
    assert cli.main(args) == 0
    assert cli.main([*args, "--memory-gb", "24"]) == 0
    out = capsys.readouterr().out
    assert "FITS: 20.00 GiB of 24.00 GiB" in out and "time (estimate)" in out
    assert cli.main([*args, "--memory-gb", "16"]) == pc.DOES_NOT_FIT
    out = capsys.readouterr().out
    assert "DOES NOT FIT: needs 20.00 GiB of 16.00 GiB" in out and "of 16.00 GiB" in out.split("Alternatives")[1]
