"""How long a forward takes on a target, estimated without the device, and what its
frame-split form sends around the ring: the `time (estimate)` and `ring` lines of `rvggt plan`.

    est = time_estimate(config, frames=4000, height=392, width=518, target="tpu-v6e", devices=8)
    est.seconds, est.floor_seconds, time_line(est, get_target("tpu-v6e"))

Time on an accelerator: the forward's FLOPs per device (`device_flops`: `estimate.forward_flops`,
i.e. `cost.cost_report`'s aggregator under the compression preset, the DINO patch embed and the
heads) at the target's peak dense FLOP/s for the way each part multiplies (`peaks.Peaks`:
the aggregator in the compute dtype, the heads in float32 at the config's precision), times
`ASSUMED_EFFICIENCY`:

    seconds = sum over parts of FLOPs / (peak x ASSUMED_EFFICIENCY)
    floor   = sum over parts of FLOPs / peak          (the compute-bound floor)

On the CPU target: `estimate.py`'s time model (its fitted efficiencies and softmax cost)
at this machine's matmul rate, measured by its probe; the floor is the FLOPs at that rate.
Neither is measured on the target: the memory traffic, the softmax, the norms, the
gathers of token merging and the exchanges between devices are not in the FLOPs.

The ring: `cost.ring_exchange`'s bytes per device and global layer at the target's link
bandwidth one way (`peaks.Link`), a floor as well (the transfers may overlap the compute,
which this does not count, or take one of several links).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rvggt_jax.config import VGGTConfig
from rvggt_jax.planning.units import fmt_bytes

__all__ = ["ASSUMED_EFFICIENCY", "TimeEstimate", "device_flops", "ring_lines", "time_estimate", "time_line"]

# The share of the peak dense FLOP/s a forward is assumed to reach on an accelerator. An
# assumption, not a measurement here: large transformer workloads reach roughly 30-55% of
# peak in practice (model FLOP utilisation: PaLM's training 46% on TPU v4, Chowdhery et al.
# 2022; Megatron-LM's 1T-parameter GPT about 52% on A100s, Narayanan et al. 2021), with
# larger matmuls than VGGT-1B's width 1024, and VGGT's forward spends time the FLOPs leave
# out (the DPT heads' memory-bound convolutions and resizes, softmax and norms, `regime`'s
# gathers, scatters and sorts). 40% sits inside that range; read the estimate as good to
# about 2x either way, and the floor (100%) as a bound no run beats.
ASSUMED_EFFICIENCY = 0.40


@dataclass(frozen=True)
class TimeEstimate:
    """One forward's estimated time on a target, per device.

    seconds        the estimate: `ASSUMED_EFFICIENCY` of the peak (accelerators), or
                   `estimate.forward_seconds` (this CPU)
    floor_seconds  the compute-bound floor: the FLOPs at the peak (at the probe's rate)
    flops          FLOPs one device computes
    parts          (what, FLOPs, FLOP/s, how it multiplies) of each part at its rate
    efficiency     ASSUMED_EFFICIENCY; None for the CPU (its model is fitted)
    devices        devices the frames are split over
    cpu_note       for the CPU: how the rate was found (else "")
    """

    seconds: float
    floor_seconds: float
    flops: float
    parts: tuple[tuple[str, float, float, str], ...]
    efficiency: float | None
    devices: int = 1
    cpu_note: str = ""


def device_flops(config: VGGTConfig, frames: int, height: int, width: int, batch: int = 1,
                 devices: int = 1) -> dict[str, float]:
    """FLOPs one device computes in a forward of `batch` sequences of `frames` frames of
    height x width split over `devices` (`estimate.forward_flops`, batch `batch`):
    "aggregator" (DINO patch embed and aggregator, in the compute dtype), "heads" (camera,
    depth, point: float32) and "total". Over devices, a device computes its
    ceil(frames / devices) frames' share (the padded share) of every part but two: the
    global layers' attention, as the split program computes it
    (`cost.device_attention_flops`: a merging layer's ring attends to every merged row, not
    only the kept K/V slots), and the camera trunk, which attends across frames and which
    `sharded_forward` runs on all frames on every device. The low-memory mode in parts
    (`model.low_memory`) computes the aggregator's first layers twice."""
    from rvggt_jax.planning.cost import cost_report, device_attention_flops
    from rvggt_jax.planning.estimate import camera_head_flops, forward_flops

    if min(frames, batch, devices) < 1:
        raise ValueError(f"frames, batch and devices must be at least 1; got {frames}, {batch}, {devices}")
    f = forward_flops(config, frames, height, width)
    camera = camera_head_flops(config, frames) if config.enable_camera else 0
    share = math.ceil(frames / devices) / frames
    aggregator = batch * (f["linear"] + f["attention"]) * share
    if devices > 1:
        split = batch * cost_report(config, frames, height, width)["global_attention_flops"]
        aggregator += sum(device_attention_flops(config, frames, height, width, devices, batch)) - split * share
    heads = batch * ((f["heads"] - camera) * share + camera)
    from rvggt_jax.model.low_memory import runs_in_parts, split_layer

    if devices == 1 and runs_in_parts(config):
        # (in parts, part 2 runs layers 0..split again: their share of the layers, taken as
        # even, once more)
        aggregator *= 1 + (split_layer(config) + 1) / config.depth
    return dict(aggregator=aggregator, heads=heads, total=aggregator + heads)


def time_estimate(config: VGGTConfig, frames: int, height: int, width: int, target, batch: int = 1,
                  devices: int = 1, rate: float | None = None,
                  efficiency: float = ASSUMED_EFFICIENCY) -> TimeEstimate | None:
    """The `TimeEstimate` of one forward of `config` on `target` (a `Target` or its name),
    frames split over `devices`; None for an accelerator whose peak is unknown
    (`Target.peak`). For the "cpu" target: `estimate.py`'s model at `rate` FLOP/s (None:
    measured now by its probe, `estimate.matmul_rate`), the whole forward (host devices
    share the cores: splitting the frames over them is no faster)."""
    from rvggt_jax.planning.targets import get_target

    target = get_target(target)
    if target.platform == "cpu":
        return _cpu_estimate(config, frames, height, width, batch, rate)
    if target.peak is None:
        return None
    if not 0 < efficiency <= 1:
        raise ValueError(f"efficiency must be in (0, 1]; got {efficiency}")
    flops = device_flops(config, frames, height, width, batch, devices)
    agg_rate, agg_how = target.peak.of(config.dtype, config.dot_precision)
    head_rate, head_how = target.peak.of("float32", config.dot_precision)
    parts = (("aggregator", flops["aggregator"], agg_rate, agg_how), ("heads", flops["heads"], head_rate, head_how))
    floor = sum(f / r for _, f, r, _ in parts)
    return TimeEstimate(floor / efficiency, floor, flops["total"], parts, efficiency, devices)


def _cpu_estimate(config, frames, height, width, batch, rate) -> TimeEstimate:
    from rvggt_jax.planning import estimate

    measured = rate is None
    rate = estimate.matmul_rate() if rate is None else rate
    flops = estimate.forward_flops(config, frames, height, width)
    note = (f"this CPU's float32 matmul rate {rate / 1e9:.0f} GFLOP/s ({'measured now by ' if measured else ''}"
            f"estimate.py's probe) and its time model fitted on float32 forwards (docs/estimate.md)")
    if config.dtype != "float32":
        note += f"; a {config.dtype} forward is not fitted"
    parts = (("forward", batch * flops["total"], rate, "float32 probe rate"),)
    return TimeEstimate(batch * estimate.forward_seconds(flops, rate), batch * flops["total"] / rate,
                        batch * flops["total"], parts, None, 1, note)


def seconds_text(seconds: float) -> str:
    """A duration to three figures: "16 us", "412 ms", "12.3 s", "4.2 min", "1.5 h"."""
    if seconds < 1e-3:
        return f"{seconds * 1e6:.3g} us"
    if seconds < 1:
        return f"{seconds * 1e3:.3g} ms"
    if seconds < 120:
        return f"{seconds:.3g} s"
    if seconds < 7200:
        return f"{seconds / 60:.3g} min"
    return f"{seconds / 3600:.3g} h"


def flop_text(n: float) -> str:
    """4.1e15, 5.9e6: two figures."""
    return f"{n:.2g}".replace("e+", "e")


def _tflops(rate: float) -> str:
    return f"{rate / 1e12:.4g} TFLOP/s" if rate >= 1e12 else f"{rate / 1e9:.4g} GFLOP/s"


def time_line(est: TimeEstimate, target) -> str:
    """The plan's line: "time (estimate) 12.3 s: ... at 40% of the H100's ... peak ...
    (compute floor 4.9 s); not measured"."""
    head = f"  time (estimate) {seconds_text(est.seconds)}"
    if est.efficiency is None:
        return (f"{head}: {flop_text(est.flops)} FLOP at {est.cpu_note} (compute floor "
                f"{seconds_text(est.floor_seconds)} at the probe's rate); not measured")
    unit = "chip" if target.platform == "tpu" else "GPU"
    per = f" per {unit} ({est.devices} of them)" if est.devices > 1 else ""
    at = ", ".join(f"{what} {flop_text(flops)} at {_tflops(rate)} {how}"
                   for what, flops, rate, how in est.parts if flops)
    return (f"{head}: {flop_text(est.flops)} FLOP{per} at {est.efficiency:.0%} (an assumed efficiency) of the "
            f"peak dense FLOP/s of one {target.name} {unit}: {at} (compute floor "
            f"{seconds_text(est.floor_seconds)}); not measured")


def _layer_ranges(layers: list[int]) -> str:
    """[0, 1, 2, 5] -> "layers 0-2, 5"; [3] -> "layer 3"."""
    runs, start = [], layers[0]
    for prev, cur in zip(layers, layers[1:] + [None]):
        if cur != prev + 1:
            runs.append(f"{start}" if start == prev else f"{start}-{prev}")
            start = cur
    return ("layers " if len(layers) > 1 else "layer ") + ", ".join(runs)


def ring_lines(exchange: list[dict], target, devices: int) -> list[str]:
    """The plan's ring lines for `cost.ring_exchange`'s layers over `devices` devices of
    `target`: per run of layers that send alike, the bytes each device sends (and
    receives) per layer, by part, and the time at the target's link one way; the sum over
    the global layers. [] on one device."""
    if devices < 2:
        return []
    link = target.link
    unit = "chip" if target.platform == "tpu" else "device"

    def at(n: float) -> str:
        return "" if link is None else f": {seconds_text(n / link.bytes_per_s)}"

    if link is None:
        where = f"the {target.name}'s interconnect bandwidth is not known here: bytes only"
    else:
        where = f"at {link.bytes_per_s / 1e9:.0f} GB/s one way, {link.source}"
        if link.links > 1:
            where += (f" (all {link.links} links at once; a ring step to one neighbour over one link: up to "
                      f"{link.links}x longer)")
    lines = [f"  ring         the frames over {devices} {unit}s: each global layer, each {unit} sends (and receives "
             f"as much) around the ring, from the layers' plans (not measured), {where}"]
    runs: dict[tuple, list[int]] = {}
    for row in exchange:
        key = (row["kind"], tuple(sorted(row["parts"].items())))
        runs.setdefault(key, []).append(row["layer"])
    for (kind, parts), layers in runs.items():
        total = sum(v for _, v in parts)
        detail = ", ".join(f"{name} {fmt_bytes(v)}" for name, v in parts) or "nothing"
        each = " each" if len(layers) > 1 else ""
        lines.append(f"               {_layer_ranges(layers)} ({kind}): {fmt_bytes(total)}{at(total)}{each} "
                     f"({detail})" if total else f"               {_layer_ranges(layers)} ({kind}): nothing")
    total = sum(row["bytes"] for row in exchange)
    lines.append(f"               sum over the {len(exchange)} global layers: {fmt_bytes(total)}{at(total)} per "
                 f"{unit} and forward (the camera head's gathers not counted)")
    return lines
