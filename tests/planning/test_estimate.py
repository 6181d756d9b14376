"""The time estimate printed before a long `rvggt reconstruct` (issue 53): the FLOP count
behind it, the cached probe, the line and when it is (not) printed. The estimate's
agreement with measured forwards is benchmarks/bench_estimate.py (docs/estimate.md)."""

import dataclasses

import pytest

from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.params import DEPTH_OUTPUT_DIM, POINT_OUTPUT_DIM
from rvggt_jax.planning import estimate
from tests.helpers import SAMPLE_IMAGES, TINY

SMALL = VGGTConfig.rvggt_small()


@pytest.fixture
def probe_calls(monkeypatch):
    """The probe replaced by a counter that reports a rate of 1 MFLOP/s (every forward
    looks long), the process cache emptied; the list of its calls."""
    calls = []

    def fake():
        calls.append(1)
        return 1e6

    monkeypatch.setattr(estimate, "_probe", fake)
    monkeypatch.setattr(estimate, "_RATES", {})
    return calls


def test_flops_grow_with_frames_and_regime_saves_at_many():
    totals = [estimate.forward_flops(SMALL, s, 168, 224) for s in (8, 32, 128)]
    assert [t["total"] for t in totals] == sorted(t["total"] for t in totals)
    # the heads and the per-frame work grow linearly, the global attention quadratically
    assert totals[2]["heads"] == pytest.approx(16 * totals[0]["heads"], rel=0.01)
    assert totals[2]["attention"] > 50 * totals[0]["attention"]
    for f in totals:
        assert f["total"] == f["linear"] + f["attention"] + f["heads"]
        assert 0 < f["scores"] * 4 * SMALL.head_dim <= f["attention"] * 1.01
    regime = estimate.forward_flops(SMALL.with_compression("regime"), 128, 168, 224)
    assert regime["attention"] < totals[2]["attention"] / 4 and regime["total"] < totals[2]["total"] / 2
    assert regime["heads"] == totals[2]["heads"]  # compression leaves the heads alone


def test_heads_follow_the_enabled_heads():
    full = estimate.forward_flops(SMALL, 8, 168, 224)["heads"]
    no_point = estimate.forward_flops(dataclasses.replace(SMALL, enable_point=False), 8, 168, 224)["heads"]
    depth = estimate.dpt_head_flops(SMALL, 8, 12, 16, DEPTH_OUTPUT_DIM)
    point = estimate.dpt_head_flops(SMALL, 8, 12, 16, POINT_OUTPUT_DIM)
    assert full == pytest.approx(no_point + point) and point > depth > 0
    tracked = estimate.forward_flops(SMALL, 8, 168, 224, with_track=True, queries=256)["heads"]
    assert tracked > full


def test_dpt_head_flops_match_xla_count(tiny):
    """The head count against XLA's cost analysis of the depth head on 2 frames (one
    group of frames: no loop whose body XLA counts once), within 10% (XLA also counts
    the elementwise work)."""
    import jax
    import jax.numpy as jnp

    from rvggt_jax.model.heads.dpt import dense_heads

    params, config = tiny
    s, hh, ww = 2, 112, 154
    grid = config.token_grid((hh, ww))
    h, w = grid.hw
    agg = {i: jax.ShapeDtypeStruct((1, s, config.patch_start_idx + h * w, 2 * config.embed_dim), jnp.float32)
           for i in config.dpt_head.intermediate_layer_idx}
    fn = jax.jit(lambda p, a: dense_heads({"depth_head": p}, a, config.dpt_head, grid))
    cost = fn.lower(params["depth_head"], agg).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    assert estimate.dpt_head_flops(config, s, h, w, DEPTH_OUTPUT_DIM) == pytest.approx(cost["flops"], rel=0.1)


def test_probe_runs_once_per_process(probe_calls):
    first = estimate.estimate_forward(SMALL, 32, 168, 224)
    again = estimate.estimate_forward(SMALL, 64, 168, 224)
    assert estimate.matmul_rate() == first.rate == again.rate == 1e6
    assert len(probe_calls) == 1


def test_the_real_probe_is_short():
    import time

    t0 = time.perf_counter()
    rate = estimate._probe()
    assert time.perf_counter() - t0 < 3.0  # ~0.3 s; a busy shared CPU stretches it
    assert 1e8 < rate < 1e15


def test_estimate_scales_with_the_rate_and_names_the_alternative():
    slow = estimate.estimate_forward(SMALL, 128, 168, 224, rate=1e10)
    fast = estimate.estimate_forward(SMALL, 128, 168, 224, rate=1e11)
    assert slow.seconds - estimate.FIXED_S == pytest.approx(10 * (fast.seconds - estimate.FIXED_S))
    assert slow.preset == "dense" and slow.alternative.preset == "regime"
    assert slow.alternative.seconds < slow.seconds / 2 and slow.alternative.alternative is None
    assert slow.alternative.compile_seconds > slow.compile_seconds  # more scanned layer runs to compile
    regime = estimate.estimate_forward(SMALL.with_compression("regime"), 128, 168, 224, rate=1e10)
    assert regime.alternative is None and regime.seconds == pytest.approx(slow.alternative.seconds)


def test_line_for_a_long_run_names_both_presets(probe_calls):
    line = estimate.long_run_line(SMALL, 128, 168, 224)
    assert line.startswith("rvggt: this run: about ") and " on this CPU (--preset regime: about " in line
    assert "compiling" in line and "\n" not in line
    assert len(probe_calls) == 1
    line = estimate.long_run_line(SMALL.with_compression("regime"), 128, 168, 224)
    assert "(--preset regime)" in line and "regime:" not in line


def test_no_line_and_no_probe_for_a_short_run(probe_calls):
    # the demo's size: the FLOP bound alone says it is short, the probe does not run
    assert estimate.long_run_line(SMALL, 8, 84, 112) is None
    assert probe_calls == []


def test_no_line_when_the_measured_rate_makes_it_short(monkeypatch):
    monkeypatch.setattr(estimate, "_probe", lambda: 1e15)
    monkeypatch.setattr(estimate, "_RATES", {})
    assert estimate.long_run_line(SMALL, 128, 168, 224) is None


@pytest.mark.parametrize("seconds, text", [(5, "about 5 s"), (44, "about 40 s"), (95, "about 2 min"),
                                           (2400, "about 40 min"), (5400, "about 1.5 h")])
def test_about(seconds, text):
    assert estimate.about(seconds) == text


def _reconstruct(tmp_path, monkeypatch, *extra):
    """`rvggt reconstruct` of the sample images with the tiny checkpoint, stopped at the
    memory check that follows the estimate (no compilation); (stdout, stderr)."""
    from rvggt_jax.app.cli import main
    from rvggt_jax.planning import memory

    def refuse(*a, **k):
        raise ValueError("stopped by the test")

    monkeypatch.setattr(memory, "check_fits", refuse)
    code = main(["reconstruct", str(SAMPLE_IMAGES), "--weights", str(TINY), "--out", str(tmp_path / "out"),
                 "--max-frames", "3", *extra])
    return code


def test_reconstruct_prints_the_line_before_a_long_run(tmp_path, monkeypatch, capsys, probe_calls):
    monkeypatch.setattr(estimate, "SLOW_RATE", 1e6)  # the tiny model's run would take minutes at 1 MFLOP/s
    assert _reconstruct(tmp_path, monkeypatch) != 0
    out, err = capsys.readouterr()
    lines = [ln for ln in out.splitlines() if "this run:" in ln]
    assert len(lines) == 1 and lines[0].startswith("rvggt: this run: about ") and "--preset regime:" in lines[0]
    assert "stopped by the test" in err
    # --quiet: nothing, not even the probe
    probe_calls.clear()
    estimate._RATES.clear()
    assert _reconstruct(tmp_path / "q", monkeypatch, "--quiet") != 0
    assert "this run" not in capsys.readouterr().out and probe_calls == []


def test_reconstruct_is_quiet_about_a_short_run(tmp_path, monkeypatch, capsys):
    """The tiny model on 3 images of 518 x 392: seconds here (the real probe, if the
    FLOP bound does not already say it is short)."""
    assert _reconstruct(tmp_path, monkeypatch) != 0
    assert "this run" not in capsys.readouterr().out
