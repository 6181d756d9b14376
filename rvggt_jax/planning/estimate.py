"""How long a forward will take on this machine, before it runs: FLOPs from the
configuration, a rate measured here.

    est = rvggt_jax.planning.estimate.estimate_forward(config, frames=32, height=168, width=224)
    est.seconds, est.compile_seconds, est.alternative   # the alternative: the same run under `regime`

Time model of one forward (jitted, float32, on a CPU):

    seconds = FIXED_S + linear / (r E_LINEAR) + (attention + SCORE_FLOPS scores) / (r E_ATTENTION)
                      + heads / (r E_HEADS)

with the FLOPs and attention logits ("scores") of `forward_flops` and r the matmul rate
of this machine, measured once per process (`matmul_rate`: the throughput of a jitted
float32 [1024, 256] x [256, 1024] product over 0.5 s, ~0.6 s with its compilation).
E_* is the fraction of the probe's rate each part reaches; SCORE_FLOPS prices a logit's
softmax (max, exp, sum, rescale) in matmul FLOPs, which is what makes attention with
small heads slow (at head dimension 16, the tiny test model's, attention runs at ~16% of
the probe's rate; at 64, VGGT-1B's, ~37%). `compile_seconds` is a base and a share per scanned run of
aggregator layers. All were fitted on a 2-core CPU shared with other jobs against
measured forwards (`benchmarks/bench_estimate.py`; the table, the fit and how far off
it is: docs/estimate.md). Where it is printed (runs of a minute or more, dominated by the
aggregator's matmuls and attention) it was within 2x of the measured time; for runs of
a second or less the per-op overheads it does not count dominate. Not
fitted: bfloat16 (`--dtype bfloat16`), GPUs (`long_run_line` says nothing off a CPU).

What `forward_flops` counts (multiply-add = 2, batch 1):
  * the aggregator and the DINOv2 patch embed: `cost.cost_report` (frame blocks, global
    blocks under the config's compression preset, patch embed);
  * the camera head: `iters` passes of its trunk (`trunk_depth` blocks of width 2E over
    the S camera tokens) and the pose MLPs;
  * the depth and point heads (each enabled one): the 4 token projections, the level
    upsamplings as the implementation runs them (x4 and x2 patchwise transposed conv +
    3x3 conv composed, `heads.resize.patchwise_conv3x3`; the stride-2 3x3 conv), the
    `layer_rn` 3x3 convs, the 4 fusion blocks (two or four 3x3 convs and a 1x1), the
    fused resize + 3x3 convs `output_conv1` and `output_conv2` (at the low resolution
    when they narrow the channels), the final 1x1 conv;
  * with `with_track`: the track head's feature DPT (the same trunk, no output conv2)
    and, roughly, its tracker (`iters` passes of the update transformer's 12 blocks over
    N x S track tokens, the correlation windows and MLP).
Not counted: normalisations, softmax, activations, bilinear resizes (as gathers and
lerps), RoPE, token merging's gathers and sorts.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from rvggt_jax.config import VGGTConfig
# upstream's fixed sizes, as the parameter layout states them: output_conv2's hidden width,
# the depth (depth + confidence) and point (xyz + confidence) heads' outputs, the
# tracker's time and space blocks
from rvggt_jax.model.params import (DEPTH_OUTPUT_DIM, DPT_HEAD_FEATURES_2, POINT_OUTPUT_DIM, TRACKER_SPACE_DEPTH,
                                    TRACKER_TIME_DEPTH)


# ---------------------------------------------------------------------------------------
# FLOPs
# ---------------------------------------------------------------------------------------


def _conv(pixels: int, k: int, cin: int, cout: int) -> int:
    return 2 * pixels * k * k * cin * cout


def _dpt_trunk_flops(config: VGGTConfig, h: int, w: int, features: int, out_channels: tuple[int, ...],
                     exact_order: bool) -> int:
    """One frame of the DPT trunk (projections to output_conv1, `dpt._fused_map`) on an
    h x w token grid. exact_order: the track head's order (plain transposed convs, then
    the 3x3 convs at the high resolution, output_conv1 after the last upsampling)."""
    e2, f, oc = 2 * config.embed_dim, features, out_channels
    hw = h * w
    flops = sum(2 * hw * e2 * c for c in oc)  # projections
    if exact_order:
        flops += 2 * hw * oc[0] * oc[0] * 16 + _conv(16 * hw, 3, oc[0], f)  # x4 transposed conv, layer1_rn
        flops += 2 * hw * oc[1] * oc[1] * 4 + _conv(4 * hw, 3, oc[1], f)  # x2, layer2_rn
    else:
        flops += 2 * hw * oc[0] * 36 * f  # patchwise x4 + 3x3: (k + 2)^2 products per input pixel
        flops += 2 * hw * oc[1] * 16 * f  # x2
    flops += _conv(hw, 3, oc[2], f)  # layer3_rn
    h3, w3 = -(-h // 2), -(-w // 2)
    flops += _conv(h3 * w3, 3, oc[3], oc[3]) + _conv(h3 * w3, 3, oc[3], f)  # stride-2 conv, layer4_rn
    # fusion blocks: refinenet4 (one residual unit) at h/2, 3, 2, 1 (two) at 1x, 2x, 4x
    flops += 2 * _conv(h3 * w3, 3, f, f) + _conv(h3 * w3, 1, f, f)
    for scale in (1, 2, 4):
        flops += 4 * _conv(hw * scale * scale, 3, f, f) + _conv(hw * scale * scale, 1, f, f)
    # output_conv1 (F -> F/2) at 8x: fused with the upsampling, the channel mix at 4x
    flops += _conv(16 * hw if not exact_order else 64 * hw, 3, f, f // 2)
    return flops


def dpt_head_flops(config: VGGTConfig, frames: int, h: int, w: int, out_dim: int) -> int:
    """One dense DPT head (depth: out_dim 2, points: 4) on `frames` frames of an h x w grid."""
    d = config.dpt_head
    f2, c2 = d.features // 2, DPT_HEAD_FEATURES_2
    full = h * w * config.patch_size ** 2
    per = _dpt_trunk_flops(config, h, w, d.features, d.out_channels, exact_order=False)
    # output_conv2: resize to H x W + 3x3 conv (F/2 -> 32), at 8x when it narrows the channels
    per += _conv(64 * h * w if f2 >= c2 else full, 3, f2, c2)
    per += 2 * full * c2 * out_dim
    return frames * per


def camera_head_flops(config: VGGTConfig, frames: int) -> int:
    """The camera head's `iters` refinement passes over the S camera tokens (width 2E)."""
    c = 2 * config.embed_dim
    cam = config.camera_head
    hidden = int(c * cam.mlp_ratio)
    block = 2 * frames * (4 * c * c + 2 * c * hidden) + 2 * 2 * frames * frames * c
    per_iter = cam.trunk_depth * block + 2 * frames * (9 * c + c * 3 * c + c * c // 2 + c // 2 * 9)
    return cam.iters * per_iter


def track_head_flops(config: VGGTConfig, frames: int, h: int, w: int, queries: int) -> int:
    """The track head, roughly: its feature DPT (exact order, at half resolution) and the
    tracker's update transformer over `queries` x `frames` tokens."""
    t = config.track_head_config
    feats = _dpt_trunk_flops(config, h, w, t.features, t.out_channels, exact_order=True)
    hid, c = t.hidden_size, t.features
    d_in = 3 * c + 4
    rows = queries * frames
    corr_in = t.corr_levels * (2 * t.corr_radius + 1) ** 2
    blocks = TRACKER_TIME_DEPTH + 3 * TRACKER_SPACE_DEPTH
    per_iter = 2 * rows * (d_in * hid + blocks * 12 * hid * hid + hid * (2 + c) + corr_in * hid + hid * c + c * c)
    per_iter += 2 * 2 * queries * frames * frames * hid * TRACKER_TIME_DEPTH  # attention over time
    per_iter += 2 * rows * t.corr_levels * (2 * t.corr_radius + 2) ** 2 * c  # correlation windows
    return frames * feats + t.iters * per_iter


def forward_flops(config: VGGTConfig, frames: int, height: int, width: int, with_track: bool = False,
                  queries: int = 0) -> dict[str, int]:
    """FLOPs of one forward (batch 1) by part: "linear" (the aggregator's and patch
    embed's projections and MLPs, the matching), "attention" (their attention matmuls),
    "heads" (camera, depth, point, track heads), "total"; and "scores", the attention
    logits computed (query x key x head: each is a softmax entry). See the module
    docstring."""
    from rvggt_jax.planning.cost import cost_report

    rep = cost_report(config, frames, height, width)
    h, w = rep["grid"]
    c = config.embed_dim
    n = 1 + config.num_register_tokens + h * w
    # attention matmuls: the global layers' (per the preset), the frame blocks', DINO's
    frame_attn = config.depth * frames * 4 * n * n * c
    dino_attn = frames * config.dino.depth * 4 * n * n * c
    attention = rep["global_attention_flops"] + frame_attn + dino_attn
    # logits: 2 (D_qk + D_v) FLOPs each; D_qk the folded head dimension in compressed layers
    scores = sum(r["attention_flops"] // (2 * (r["head_dim_qk"] + config.head_dim)) for r in rep["layers"])
    scores += (frame_attn // (4 * config.head_dim) + dino_attn // (4 * (c // config.dino.num_heads)))
    aggregator = rep["aggregator_flops"] + rep["patch_embed_flops"]
    heads = camera_head_flops(config, frames) if config.enable_camera else 0
    heads += dpt_head_flops(config, frames, h, w, DEPTH_OUTPUT_DIM) if config.enable_depth else 0
    heads += dpt_head_flops(config, frames, h, w, POINT_OUTPUT_DIM) if config.enable_point else 0
    if with_track and config.enable_track:
        heads += track_head_flops(config, frames, h, w, queries)
    return dict(linear=aggregator - attention, attention=attention, heads=heads, total=aggregator + heads,
                scores=scores)


# ---------------------------------------------------------------------------------------
# The rate of this machine
# ---------------------------------------------------------------------------------------

# The probe: a jitted float32 [PROBE_ROWS, PROBE_WIDTH] x [PROBE_WIDTH, 4 PROBE_WIDTH]
# product (an MLP's first matmul at width 256, ~2 ms on a 2-core CPU) run back to back for
# PROBE_SECONDS after one warm-up run: its throughput. ~0.6 s with the compilation. (On a
# CPU shared with other jobs the rate moves from second to second; over 0.5 s it moved
# half as much as over 0.2 s: docs/estimate.md.)
PROBE_ROWS, PROBE_WIDTH, PROBE_SECONDS = 1024, 256, 0.5
_RATES: dict[str, float] = {}
_RATES_LOCK = threading.Lock()


def _probe() -> float:
    """FLOP/s of the probe product on JAX's default device, measured now."""
    import jax
    import jax.numpy as jnp

    x = jnp.full((PROBE_ROWS, PROBE_WIDTH), 0.5, jnp.float32)
    w = jnp.full((PROBE_WIDTH, 4 * PROBE_WIDTH), 0.01, jnp.float32)
    f = jax.jit(lambda a, b: jnp.dot(a, b, precision=jax.lax.Precision.HIGHEST))
    jax.block_until_ready(f(x, w))
    runs, t0 = 0, time.perf_counter()
    while True:
        jax.block_until_ready(f(x, w))
        runs += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= PROBE_SECONDS:
            return runs * 2 * PROBE_ROWS * PROBE_WIDTH * 4 * PROBE_WIDTH / elapsed


def matmul_rate() -> float:
    """This process's float32 matmul rate (FLOP/s) on JAX's default device: measured
    once (`_probe`), then cached."""
    import jax

    key = jax.default_backend()
    with _RATES_LOCK:
        if key not in _RATES:
            _RATES[key] = _probe()
        return _RATES[key]


# ---------------------------------------------------------------------------------------
# The time model
# ---------------------------------------------------------------------------------------

# Fitted on a 2-core Xeon shared with other jobs (docs/estimate.md: the cases, the fit):
# the fraction of the probe's rate each part reaches, the softmax cost of a logit in
# matmul FLOPs, the per-forward overhead, and the compilation time (seconds: a base and
# one per extra `lax.scan` of aggregator layers, `model.aggregator.layer_groups`; XLA
# compiles on one core, so this is this machine's and does not scale with the probe)
E_LINEAR = 0.69
E_ATTENTION = 0.65
SCORE_FLOPS = 196.0
E_HEADS = 0.44
FIXED_S = 0.14
COMPILE_BASE_S = 25.0
COMPILE_PER_GROUP_S = 5.0

# Where `rvggt reconstruct` prints the estimate: a forward expected to take longer
LONG_RUN_S = 60.0
# A rate no CPU that runs the model falls below (FLOP/s): a forward whose time at this
# rate stays under LONG_RUN_S is short anywhere, and the probe is not run for it
SLOW_RATE = 5e9
# The preset an estimate of a dense run names as the faster alternative
ALTERNATIVE = "regime"


@dataclass(frozen=True)
class Estimate:
    """One forward's expected time on this machine.

    preset           the config's compression preset
    seconds          the forward, compiled
    compile_seconds  compiling it for a new input shape (skipped when the persistent
                     compilation cache holds the program: the same shape run before)
    flops            `forward_flops` by part
    rate             the probe's FLOP/s (`matmul_rate`)
    alternative      the same run under `ALTERNATIVE` (when the preset is dense), or None
    """

    preset: str
    seconds: float
    compile_seconds: float
    flops: dict
    rate: float
    alternative: "Estimate | None" = None


def forward_seconds(flops: dict, rate: float) -> float:
    """The time model (module docstring) for `forward_flops`' parts at `rate` FLOP/s."""
    return (FIXED_S + flops["linear"] / (rate * E_LINEAR)
            + (flops["attention"] + SCORE_FLOPS * flops["scores"]) / (rate * E_ATTENTION)
            + flops["heads"] / (rate * E_HEADS))


def compile_seconds(config: VGGTConfig, frames: int, height: int, width: int) -> float:
    """Compiling the forward: a base and a share per scanned run of aggregator layers
    (one when dense; a compression preset's bands add runs)."""
    from rvggt_jax.compression.partition import Geometry
    from rvggt_jax.model.aggregator import layer_groups

    ps = config.patch_size
    geom = Geometry(frames, height // ps, width // ps, config.patch_start_idx)
    return COMPILE_BASE_S + COMPILE_PER_GROUP_S * (len(layer_groups(config, geom)) - 1)


def estimate_forward(config: VGGTConfig, frames: int, height: int, width: int, *, rate: float | None = None,
                     alternative: str | None = ALTERNATIVE, with_track: bool = False,
                     queries: int = 0) -> Estimate:
    """The `Estimate` of one forward of `config` on `frames` images of height x width
    (multiples of the patch size); `rate`: FLOP/s (None: `matmul_rate()`, measured once
    per process); `alternative`: a preset also estimated when the config is dense (None:
    none)."""
    rate = matmul_rate() if rate is None else rate
    flops = forward_flops(config, frames, height, width, with_track, queries)
    alt = None
    if alternative is not None and config.compression.is_dense and alternative != config.compression.name:
        other = config.with_compression(alternative)
        alt = estimate_forward(other, frames, height, width, rate=rate, alternative=None, with_track=with_track,
                               queries=queries)
    return Estimate(config.compression.name, forward_seconds(flops, rate),
                    compile_seconds(config, frames, height, width), flops, rate, alt)


def about(seconds: float) -> str:
    """"about 40 s", "about 3 min", "about 1.5 h": a duration to the precision the model has."""
    if seconds < 90:
        return f"about {int(seconds / 10 + 0.5) * 10 if seconds >= 9.5 else max(1, int(seconds + 0.5))} s"
    minutes = seconds / 60
    if minutes < 90:
        return f"about {int(minutes + 0.5)} min"
    return f"about {minutes / 60:.1f} h"


def long_run_line(config: VGGTConfig, frames: int, height: int, width: int,
                  threshold: float = LONG_RUN_S) -> str | None:
    """The line `rvggt reconstruct` prints before a forward expected to take more than
    `threshold` seconds on this CPU, else None. The probe runs only when the forward
    could be long: its time at `SLOW_RATE` is the bound that says it is not. None off a
    CPU (the efficiency factors were fitted on one) and when the estimate cannot be made."""
    import jax

    if jax.default_backend() != "cpu":
        return None
    try:
        if forward_seconds(forward_flops(config, frames, height, width), SLOW_RATE) < threshold:
            return None
        est = estimate_forward(config, frames, height, width)
    except Exception:  # noqa: BLE001 - an estimate is advice: it never stops a run
        return None
    if est.seconds < threshold:
        return None
    line = f"rvggt: this run: {about(est.seconds)} on this CPU"
    if est.preset != "dense":
        line += f" (--preset {est.preset})"
    alt = est.alternative
    if alt is not None and alt.seconds < 0.8 * est.seconds:
        line += f" (--preset {alt.preset}: {about(alt.seconds)})"
    return line + f", plus {about(est.compile_seconds)} compiling the first time"
