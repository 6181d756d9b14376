"""`rvggt plan`'s time estimate and ring lines (rvggt_jax.planning.target_time, cost.ring_exchange):
the FLOPs at the target's peak and the assumed efficiency, per device over devices; the bytes
each device sends per global layer, checked by hand and against what the traced sharded
forward exchanges (its collectives in the jaxpr, a deviceless TPU slice: no compile)."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.config import VGGTConfig
from rvggt_jax.diagnostics.presets_io import resolve_preset
from rvggt_jax.planning import cost, estimate
from rvggt_jax.planning import target_time as tt
from rvggt_jax.planning import targets as tg
from rvggt_jax.planning.cost import cost_report, device_attention_flops, ring_exchange
from tests.helpers.micro import plan_config

GiB = 2 ** 30


@pytest.fixture
def round_flops(monkeypatch):
    """`forward_flops` of any forward: 3e12 linear + 1e12 attention (the aggregator, 0.8e12
    of it the global layers' attention on one device, 0.2e12 on each device over several),
    2e12 in the heads of which 0.5e12 in the camera head; the numbers below are worked by hand."""
    flops = dict(linear=3e12, attention=1e12, heads=2e12, total=6e12, scores=1e9)
    monkeypatch.setattr(estimate, "forward_flops", lambda *a, **k: dict(flops))
    monkeypatch.setattr(estimate, "camera_head_flops", lambda *a, **k: 0.5e12)
    monkeypatch.setattr(cost, "cost_report", lambda *a, **k: dict(global_attention_flops=0.8e12))
    monkeypatch.setattr(cost, "device_attention_flops", lambda *a, **k: [0.05e12] * 4)
    return flops


BF16 = dataclasses.replace(VGGTConfig.vggt_1b(), enable_track=False).with_dtype("bfloat16")
F32 = BF16.with_dtype("float32")


def test_the_estimate_is_the_flops_at_the_peak_times_the_assumed_efficiency(round_flops):
    assert tt.ASSUMED_EFFICIENCY == 0.40
    # H100, bf16: 4e12 at 989.4 TFLOP/s (bf16), 2e12 at 494.7 (the float32 heads on TF32)
    est = tt.time_estimate(BF16, 100, 392, 518, "h100")
    assert est.flops == 6e12
    assert est.floor_seconds == pytest.approx(4 / 989.4 + 2 / 494.7)  # 8.0857 ms
    assert est.floor_seconds == pytest.approx(8.08571e-3, rel=1e-5)
    assert est.seconds == pytest.approx(20.2143e-3, rel=1e-5)  # the floor / 0.4
    # float32 at "highest": no TF32, the 66.9 TFLOP/s of the CUDA cores for all 6e12
    assert tt.time_estimate(F32, 100, 392, 518, "h100").seconds == pytest.approx(6 / 66.9 / 0.4, rel=1e-9)
    # a TPU runs a float32 product at highest as six bf16 passes: 918 / 6 = 153 TFLOP/s; its
    # heads at the default (one pass) in a bf16 config
    assert tt.time_estimate(F32, 100, 392, 518, "tpu-v6e").floor_seconds == pytest.approx(6 / 153, rel=1e-9)
    assert tt.time_estimate(BF16, 100, 392, 518, "tpu-v6e").floor_seconds == pytest.approx(6 / 918, rel=1e-9)
    # batch 3: three times the work
    assert tt.time_estimate(BF16, 100, 392, 518, "h100", batch=3).seconds == pytest.approx(3 * est.seconds)


def test_over_devices_each_computes_its_share_and_the_whole_camera_trunk(round_flops):
    # 4000 frames over 8 v6e chips: (4 - 0.8)e12 / 8 + 0.2e12 = 0.6e12 of aggregator (the global
    # attention as the split program computes it), (2 - 0.5)e12 / 8 + 0.5e12 = 0.6875e12 of
    # heads (the camera trunk runs on every chip for all frames)
    est = tt.time_estimate(BF16, 4000, 392, 518, "tpu-v6e", devices=8)
    assert est.flops == pytest.approx(1.2875e12)
    assert est.floor_seconds == pytest.approx(1.2875 / 918, rel=1e-9)
    assert est.seconds == pytest.approx(3.50626e-3, rel=1e-5)
    # 10 frames over 4 devices: each holds 3 (the padded share), 0.3 of the split work
    flops = tt.device_flops(BF16, 10, 392, 518, devices=4)
    assert flops == pytest.approx(dict(aggregator=1.16e12, heads=0.95e12, total=2.11e12))
    line = tt.time_line(est, tg.TARGETS["tpu-v6e"])
    for part in ("time (estimate) 3.51 ms: 1.3e12 FLOP per chip (8 of them) at 40% (an assumed efficiency)",
                 "918 TFLOP/s bf16", "one bf16 pass", "(compute floor 1.4 ms); not measured"):
        assert part in line, (part, line)


def test_over_devices_a_merging_layer_attends_to_every_merged_row():
    base = VGGTConfig(embed_dim=256, num_heads=4).with_compression("regime")
    one = device_attention_flops(base, 64, 168, 224, 1)
    assert one == [r["attention_flops"] for r in cost_report(base, 64, 168, 224)["layers"]]
    four = device_attention_flops(base, 64, 168, 224, 4)
    # layer 0: 4733 merged rows (tests/planning/test_cost.py), 1184 on a device, against all
    # 4 x 1184 (the K/V slots the layer does not keep are masked, not dropped), 4 heads of 64
    # and the size column
    assert four[0] == 2 * 1184 * 4736 * 4 * (65 + 64) == 5_786_861_568
    assert 4 * four[0] > 1.5 * one[0]
    # dense: 16 frames of 197 tokens, 4 on a device, against the 16 x 197 of the sequence
    dense = device_attention_flops(base.with_compression("dense"), 16, 168, 224, 4)
    assert dense == [2 * 788 * 3152 * 4 * 128] * 24
    # the per-device FLOPs take the split attention: more than a quarter of one device's
    full, split = (tt.device_flops(base, 64, 168, 224, devices=n)["aggregator"] for n in (1, 4))
    assert split - full / 4 == pytest.approx(sum(four) - sum(one) / 4)


def test_the_cpu_estimate_is_estimate_py_s_model_at_the_probe_rate(round_flops):
    est = tt.time_estimate(F32, 10, 392, 518, "cpu", rate=1e11, batch=2)
    assert est.floor_seconds == pytest.approx(2 * 6e12 / 1e11) == 120.0
    assert est.seconds == pytest.approx(2 * estimate.forward_seconds(round_flops, 1e11))
    assert est.efficiency is None
    line = tt.time_line(est, tg.TARGETS["cpu"])
    assert "time (estimate)" in line and "100 GFLOP/s" in line and "probe" in line and "not measured" in line
    assert "not fitted" in tt.time_line(tt.time_estimate(BF16, 10, 392, 518, "cpu", rate=1e11), tg.TARGETS["cpu"])


def test_a_target_without_a_known_peak_gets_no_estimate():
    mine = dataclasses.replace(tg.TARGETS["h100"], name="my-card", peak=None)
    assert tt.time_estimate(plan_config(), 2, 28, 42, mine) is None


def test_the_target_table_holds_the_vendors_figures():
    t = tg.TARGETS
    assert t["h100"].peak.bf16 == t["h200"].peak.bf16 == pytest.approx(989.4e12)
    assert t["h100"].peak.of("float32", "highest") == (pytest.approx(66.9e12), "float32 at highest (FP32, no TF32)")
    assert t["h100"].peak.of("float32", None) == (pytest.approx(494.7e12), "float32 at default (TF32)")
    assert [t[n].peak.bf16 for n in ("tpu-v6e", "tpu-v5e", "tpu-v5p")] == pytest.approx([918e12, 197e12, 459e12])
    assert t["tpu-v6e"].peak.of("float32", "highest")[0] == pytest.approx(153e12)  # six bf16 passes
    assert t["tpu-v6e"].peak.of("float32", "high")[0] == pytest.approx(306e12)  # three
    assert t["h100"].peak.of("float32", "high")[0] == pytest.approx(494.7e12)  # TF32
    assert t["tpu-v6e"].link.bytes_per_s == 400e9 and t["tpu-v6e"].link.links == 4  # 800 GB/s both ways
    assert t["h100"].link.bytes_per_s == 450e9  # NVLink 900 GB/s both ways
    assert all(x.peak is not None and x.link is not None for x in t.values() if x.platform != "cpu")
    assert "800 GB/s" in t["tpu-v6e"].link.source


# ---------------------------------------------------------------------------------------
# The ring
# ---------------------------------------------------------------------------------------


def test_a_dense_layer_passes_every_other_devices_k_and_v():
    # 16 frames of 1041 tokens (5 + 28 x 37) over 4 devices: 4 frames each, 3 ring steps of
    # K and V [1, 4164, 1024] in bf16
    ex = ring_exchange(BF16, 16, 392, 518, devices=4)
    assert len(ex) == 24 and all(r["kind"] == "dense" for r in ex)
    assert all(r["parts"] == {"K/V": 3 * 4 * 1041 * 1024 * 2 * 2} for r in ex)
    assert ex[0]["bytes"] == 51_167_232
    # 15 frames: the last device holds a padding frame, and the float32 mask travels too
    assert ring_exchange(BF16, 15, 392, 518, devices=4)[0]["bytes"] == 3 * 4 * 1041 * (4096 + 4) == 51_217_200
    assert ring_exchange(F32, 16, 392, 518, devices=4)[0]["bytes"] == 2 * 51_167_232
    assert all(r["bytes"] == 0 for r in ring_exchange(BF16, 16, 392, 518, devices=1))


def test_a_kv_layer_all_reduces_its_kept_float32_rows():
    cfg = dataclasses.replace(BF16, compression=resolve_preset("avggt", 24))
    ex = ring_exchange(cfg, 16, 392, 518, devices=4)
    assert [r["kind"] for r in ex] == ["frame"] * 9 + ["kv"] * 15 and ex[0]["bytes"] == 0
    # a 2 x 2 sub-grid: of every frame its 5 special tokens and 14 x 18 of its 28 x 37 patches,
    # frame 0 not anchored (avggt): 16 x (5 + 252) = 4112 rows of 1024 float32, of which a ring
    # all-reduce sends 2 (4 - 1) / 4 = 1.5 times
    assert ex[9]["parts"] == {"kept rows": pytest.approx(1.5 * 4112 * 1024 * 4)}


def test_the_ring_lines_name_the_bytes_the_time_and_the_link():
    ex = ring_exchange(BF16, 16, 392, 518, devices=4)
    lines = tt.ring_lines(ex, tg.TARGETS["tpu-v6e"], 4)
    text = "\n".join(lines)
    assert lines[0].startswith("  ring         the frames over 4 chips") and "400 GB/s one way" in text
    # 48.80 MiB at 400e9 B/s: 128 us per layer, 24 of them 3.07 ms
    assert "layers 0-23 (dense): 48.80 MiB: 128 us each (K/V 48.80 MiB)" in text, text
    assert "sum over the 24 global layers: 1.14 GiB: 3.07 ms per chip" in text, text
    assert tt.ring_lines(ex, tg.TARGETS["tpu-v6e"], 1) == []


def _exchanged(jaxpr, devices: int, in_layers: bool = False) -> float:
    """Bytes one device sends through the collectives of `jaxpr` inside the aggregator's
    scanned layers (`in_layers`: under a scan; the per-forward gathers sit outside): a
    permute its operand, an all-gather D - 1 operands, an all-reduce 2 (D - 1) / D; a
    `cond` its largest branch (`platform_dependent`'s CPU and TPU forms move the same
    bytes), a scan its body times its length."""
    from jax.extend import core

    total = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        size = sum(np.prod(v.aval.shape) * v.aval.dtype.itemsize for v in eqn.invars if hasattr(v.aval, "shape"))
        if name in ("ppermute", "all_gather", "psum") and in_layers:
            total += {"ppermute": 1, "all_gather": devices - 1, "psum": 2 * (devices - 1) / devices}[name] * size
        assert name not in ("all_to_all", "psum_scatter", "reduce_scatter", "while"), name  # none expected
        subs = [p.jaxpr if isinstance(p, core.ClosedJaxpr) else p
                for v in eqn.params.values() for p in (v if isinstance(v, (tuple, list)) else (v,))
                if isinstance(p, (core.ClosedJaxpr, core.Jaxpr))]
        inner = [_exchanged(s, devices, in_layers or name == "scan") for s in subs]
        if name == "cond":
            total += max(inner)
        elif name == "scan":
            total += eqn.params["length"] * sum(inner)
        else:
            total += sum(inner)
    return total


@pytest.mark.parametrize("preset", ["dense", "regime", "regime_local", "avggt"])
def test_the_counted_bytes_are_what_the_sharded_forward_exchanges(preset):
    pytest.importorskip("libtpu")
    from rvggt_jax.parallel.sharded import sharded_forward
    from rvggt_jax.planning.memory import abstract_params

    cfg = plan_config()
    cfg = dataclasses.replace(cfg, compression=resolve_preset(preset, cfg.depth)).with_dtype("bfloat16")
    frames, devices = 7, 4  # (one padding frame)
    mesh = jax.sharding.Mesh(np.asarray(tg.target_devices("tpu-v6e", devices)), ("frames",),
                             axis_types=(jax.sharding.AxisType.Auto,))
    images = jax.ShapeDtypeStruct((1, frames, 3, 28, 42), jnp.uint8)
    traced = jax.make_jaxpr(functools.partial(sharded_forward, config=cfg, mesh=mesh))(
        abstract_params(cfg, param_dtype="bfloat16"), images)
    counted = sum(r["bytes"] for r in ring_exchange(cfg, frames, 28, 42, devices))
    assert counted > 0
    assert _exchanged(traced.jaxpr, devices) == pytest.approx(counted, rel=1e-12)
