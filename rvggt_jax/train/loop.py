"""`rvggt finetune DATA_DIR --out OUT`: fine-tune on a folder of scenes in any format the
evaluation reads (folder, CO3D, ScanNet, 7 Scenes, NRGBD, DTU, COLMAP; `rvggt_jax.train.data`),
resumable exactly.

OUT/state/<step>/   Orbax train state (params + optimiser + step); a rerun with the same
                    OUT resumes from the newest one and continues exactly as the
                    uninterrupted run (step i's batch is drawn from (seed, i) alone)
OUT/train.json      the model and train configs
OUT/model/          the fine-tuned weights (`save_orbax`: `rvggt reconstruct --weights OUT/model`)
OUT/log.jsonl       one line of metrics per logged step (a resumed run drops the lines past
                    its checkpoint first)
OUT/loss.png        the loss curve (the objective per logged step), redrawn as it goes

Shapes are static: each step's frame count is drawn in `FinetuneOptions.frames` and
rounded down to one of a few buckets, one compiled program per bucket
(`BucketedStep`; docs/training.md, "Frame counts").
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import jax
import numpy as np

from rvggt_jax.config import VGGTConfig
from rvggt_jax.errors import InputError
from rvggt_jax.train import data as data_mod
from rvggt_jax.train.step import (TrainConfig, divisors, init_state, latest_step, make_train_step, restore_state,
                                  save_state)


@dataclasses.dataclass(frozen=True)
class FinetuneOptions:
    """What `finetune` runs (the CLI's options).

    frames: a fixed count, or a (min, max) range drawn per step (upstream: 2..24);
    buckets: the frame counts compiled (default `data.default_buckets`: the range's ends
    and the powers of two between); data_format: a name of `data.TRAIN_FORMATS` or "auto";
    stop_at: stop after this step (the state saved; a rerun continues, as if never
    stopped); prefetch: batches read ahead by a background thread."""

    steps: int = 1000
    frames: int | tuple[int, int] = (2, 24)
    size: tuple[int, int] = (224, 294)
    batch: int = 1
    accumulate: int = 1  # micro-batches per step: `batch` scenes, `batch / accumulate` at a time
    # over many devices (rvggt_jax.train.sharded): mesh "data" x "frames", frames / frames_per_device
    # devices per scene (a split of the frames needs a fixed frame count); fsdp: the train
    # state split over all of them
    devices: int = 1
    frames_per_device: int | None = None
    fsdp: bool = False
    learning_rate: float = 1e-5
    warmup_steps: int | None = None  # default: 10% of the steps, at most 500
    train: str | tuple[str, ...] = "all"
    preset: str | None = None
    dtype: str = "float32"
    remat: bool | str = False  # VGGTConfig.remat: a policy name, True ("full") or False ("none")
    save_every: int = 500
    log_every: int = 10
    seed: int = 0
    buckets: tuple[int, ...] | None = None
    data_format: str = "auto"
    require_depth: bool = False
    stop_at: int | None = None
    prefetch: int = 2


class BucketedStep:
    """The jitted train step, called only with the shapes it was planned for: B scenes
    of one of `buckets` frame counts at `size`. A call that compiles a program says so
    (`log`, with its time); a batch of another shape is an InputError naming the planned
    ones (never a silent recompile). `compiled()`: the programs jit holds."""

    def __init__(self, fn, batch: int, buckets: Sequence[int], size: tuple[int, int], log=print):
        self.fn, self.batch, self.buckets, self.size, self.log = fn, batch, tuple(buckets), tuple(size), log
        self.seen: set[tuple[int, ...]] = set()

    def __call__(self, state, batch: dict):
        shape = tuple(batch["images"].shape)
        if len(shape) != 5:
            raise InputError(f"a batch's images must be [B, S, 3, H, W]; got shape {shape}")
        b, s, _, h, w = shape
        if b != self.batch or s not in self.buckets or (h, w) != self.size:
            raise InputError(f"a batch of {b} x {s} frames of {h}x{w} differs from the compiled train step "
                             f"({self.batch} x {list(self.buckets)} frames of {self.size[0]}x{self.size[1]})")
        if shape in self.seen:
            return self.fn(state, batch)
        self.seen.add(shape)
        before, t0 = self.compiled(), time.perf_counter()
        result = self.fn(state, batch)
        if self.compiled() > before:
            self.log(f"compiled the train step for {s} frames of {h}x{w} in {time.perf_counter() - t0:.1f} s "
                     f"(program {self.compiled()} of at most {len(self.buckets)})")
        return result

    def compiled(self) -> int:
        """The programs the jitted step holds (one per shape it was called with)."""
        size = getattr(self.fn, "_cache_size", None)
        return size() if size is not None else len(self.seen)


_STEPS: dict = {}


def cached_train_step(config: VGGTConfig, tc: TrainConfig):
    """`make_train_step(config, tc)`, one per (config, tc) in this process: a rerun or a
    resumed run in the same process reuses the programs already compiled."""
    key = (config, tc)
    if key not in _STEPS:
        if len(_STEPS) >= 4:
            _STEPS.pop(next(iter(_STEPS)))
        _STEPS[key] = make_train_step(config, tc)
    return _STEPS[key]


def load_model(weights: str | None, config_json: str | None, seed: int) -> tuple[dict, VGGTConfig]:
    """(params, config): a checkpoint (anything `load_pretrained` reads) or, with only a
    config.json, upstream's random initialisation."""
    import rvggt_jax

    if weights:
        return rvggt_jax.load_pretrained(weights)
    if config_json:
        config = VGGTConfig.from_json(config_json)
        return rvggt_jax.init_params(config, seed), config
    raise InputError("give --weights (a checkpoint to fine-tune) or --config (a config.json: random init)")


def device_layout(opts: FinetuneOptions):
    """The devices' layout for `opts` (`rvggt_jax.train.sharded.TrainLayout`), None for one
    device; an InputError saying what would work when it does not fit. A split of each
    scene's frames (`frames_per_device`) needs one frame count for every step: with
    several buckets the frame axis would change size between steps."""
    if not (opts.devices > 1 or opts.fsdp or opts.frames_per_device is not None):
        return None
    from rvggt_jax.train.sharded import train_layout

    lo, hi, buckets = data_mod.frame_plan(opts.frames, opts.buckets)
    if opts.frames_per_device is not None and len(buckets) > 1:
        raise InputError(f"--frames-per-device splits a fixed frame count over devices; --frames {lo}-{hi} "
                         f"draws {list(buckets)}: give one count (--frames N), or leave --frames-per-device "
                         f"out (each scene on one device, the scenes over the devices)")
    return train_layout(opts.devices, opts.batch, buckets[0], opts.frames_per_device,
                        accumulate=opts.accumulate, fsdp=opts.fsdp)


def _train_step(config: VGGTConfig, tc: TrainConfig, layout, state, log):
    """(step(state, batch), state placed for it): the one-device jitted step (the state
    committed to the device), or over `layout`'s mesh the sharded step, which places each
    host batch on the mesh (the state placed by `place_state`)."""
    if layout is None:
        # every leaf a jax.Array committed to the device: the state a step returns is, and a
        # fresh one (numpy or uncommitted parameters) or a restored one must have the same
        # signature, or jit compiles the step again for it
        return cached_train_step(config, tc), jax.device_put(state, jax.devices()[0])
    from rvggt_jax.train import sharded as multi

    mesh = multi.train_mesh(layout)
    sharded_step = multi.make_sharded_train_step(config, tc, mesh, fsdp=layout.fsdp)
    log(f"training on {layout.describe()}")
    return (lambda st, b: sharded_step(st, multi.place_batch(b, mesh))), multi.place_state(state, mesh, layout.fsdp)


def finetune(data_dir: str | Path, out: str | Path, params: dict, config: VGGTConfig, opts: FinetuneOptions,
             log: Callable[[str], Any] = print, progress: bool = True) -> Path:
    """Train `params` on the scenes of `data_dir` for `opts.steps` steps (resuming from
    `out` when it holds a train state; stopping early at `opts.stop_at`); returns
    OUT/model (written when the run reaches `opts.steps`, else OUT/state's newest step).
    `progress`: a tqdm bar on stderr. The train step donates its state: `params`' device
    buffers are reused by the first step (pass a copy to keep them)."""
    out = Path(out)
    if opts.steps < 1 or opts.batch < 1:
        raise InputError(f"steps and batch must be >= 1; got {opts.steps}, {opts.batch}")
    lo, hi, buckets = data_mod.frame_plan(opts.frames, opts.buckets)
    if opts.accumulate < 1 or opts.batch % opts.accumulate:
        raise InputError(f"--accumulate {opts.accumulate} must divide --batch {opts.batch} (micro-batches of "
                         f"batch / accumulate scenes): --batch {opts.batch} takes --accumulate in "
                         f"{divisors(opts.batch)}")
    layout = device_layout(opts)  # (checked before reading data)
    data_mod._check_size(opts.size)
    fmt, scenes = data_mod.open_scenes(data_dir, opts.data_format, require_depth=opts.require_depth, log=log)
    usable = [s for s in scenes if len(s) >= lo]
    if not usable:
        raise InputError(f"no scene in {data_dir} has {lo} frames (--frames); they have "
                         f"{sorted(len(s) for s in scenes)}")
    if opts.preset:
        config = config.with_compression(opts.preset)
    config = config.with_dtype(opts.dtype).with_remat(opts.remat)
    warmup = opts.warmup_steps if opts.warmup_steps is not None else min(500, opts.steps // 10)
    tc = TrainConfig(learning_rate=opts.learning_rate, warmup_steps=warmup, total_steps=opts.steps,
                     train=opts.train, accumulate=opts.accumulate).validate()

    def make(i: int) -> dict:
        return data_mod.step_batch(usable, i, opts.seed, opts.batch, (lo, hi), opts.size, buckets)

    return run_training(out, params, config, tc, opts, make, buckets,
                        f"{len(usable)} {fmt} scenes in {data_dir}", log=log, progress=progress)


def run_training(out: Path, params: dict, config: VGGTConfig, tc: TrainConfig, opts: FinetuneOptions,
                 make: Callable[[int], dict], buckets: Sequence[int], source: str,
                 log: Callable[[str], Any] = print, progress: bool = True, desc: str = "finetune") -> Path:
    """The training loop behind `finetune` and `rvggt_jax.train.small`: `opts.steps` steps
    of `tc` on the batches `make(step)` (a function of the step alone), resuming from
    OUT/state, checkpointing every `opts.save_every` steps, logging to OUT/log.jsonl and
    OUT/loss.png; OUT/model at the end. `source` describes the data in the log."""
    lo, hi = min(buckets), max(buckets)
    saved = latest_step(out)
    if saved is not None:
        # the saved state replaces every leaf: a fresh one's shapes are enough (no second
        # optimiser state is allocated; `params` may be shapes, `jax.eval_shape`'s)
        state = restore_state(out, jax.eval_shape(lambda p: init_state(p, tc), params))
    else:
        state = init_state(params, tc)
    start = int(state.step)
    stop = min(opts.steps, opts.stop_at) if opts.stop_at is not None else opts.steps
    if saved is not None:
        if start < opts.steps:
            _say_if_replanned(out, tc, start, log)
        if start >= stop:
            return _nothing_to_train(out, state, config, opts, start, log)
        log(f"resuming from step {start} in {out}")
    fn, state = _train_step(config, tc, device_layout(opts), state, log)
    step_fn = BucketedStep(fn, opts.batch, buckets, opts.size, log)
    log(f"{source}; {lo}..{hi} frames per step in buckets {list(buckets)}")

    out.mkdir(parents=True, exist_ok=True)
    history = _read_log(out / "log.jsonl", upto=start)
    _write_log(out / "log.jsonl", history)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=opts.steps, initial=start, unit="step", desc=desc, dynamic_ncols=True)
        if log is print:
            log = bar.write
        step_fn.log = log
    stream = data_mod.BatchStream(make, start, stop, opts.prefetch)
    t0 = time.perf_counter()
    try:
        with open(out / "log.jsonl", "a") as logf:
            for i, batch in stream:
                state, metrics = step_fn(state, batch)
                if bar is not None:
                    bar.update(1)
                if (i + 1) % opts.log_every == 0 or i + 1 == stop or i == start:
                    m = {k: float(v) for k, v in jax.device_get(metrics).items()}
                    rec = {"step": i + 1, "frames": int(batch["images"].shape[1]), **m}
                    history.append(rec)
                    logf.write(json.dumps(rec) + "\n")
                    logf.flush()
                    if bar is not None:
                        bar.set_postfix(loss=f"{m['loss_objective']:.4f}", frames=rec["frames"], refresh=False)
                    log(f"step {i + 1}/{opts.steps}  loss {m['loss_objective']:.4f}  lr {m['lr']:.2e}  "
                        f"grad norm {m['grad_norm']:.3f}  frames {rec['frames']}  ({time.perf_counter() - t0:.0f} s)")
                if (i + 1) % opts.save_every == 0 and i + 1 < stop:
                    save_state(state, out, model_config=config, train_config=tc)
                    plot_loss(history, out / "loss.png")
    finally:
        stream.close()
        if bar is not None:
            bar.close()
    save_state(state, out, model_config=config, train_config=tc)
    plot_loss(history, out / "loss.png")
    if stop < opts.steps:
        log(f"stopped after step {stop} of {opts.steps}; rerun with the same --out to continue")
        return out / "state" / str(stop)

    from rvggt_jax.weights.checkpoint import save_orbax

    model_dir = save_orbax(jax.device_get(state.params), config, out / "model", overwrite=True)
    log(f"fine-tuned weights: {model_dir} (rvggt reconstruct --weights {model_dir})")
    return model_dir


def _nothing_to_train(out: Path, state, config: VGGTConfig, opts: FinetuneOptions, start: int, log) -> Path:
    """A rerun whose state is already at its last step (finished, or at --stop-at): says
    so and trains nothing; a finished run's OUT/model is written if it is missing (a run
    stopped between its last state and its weights). Returns what `finetune` returns."""
    if start < opts.steps:
        log(f"already at step {start} of {opts.steps} (--stop-at {opts.stop_at}): nothing to train; rerun with a "
            f"later --stop-at, or without it, to continue")
        return out / "state" / str(start)
    model_dir = out / "model"
    if not (model_dir / "config.json").is_file():
        from rvggt_jax.weights.checkpoint import save_orbax

        save_orbax(jax.device_get(state.params), config, model_dir, overwrite=True)
    log(f"finished: {out} holds step {start} (--steps {opts.steps}): nothing to train; fine-tuned weights: "
        f"{model_dir} (a larger --steps continues the run)")
    return model_dir


def _say_if_replanned(out: Path, tc: TrainConfig, start: int, log) -> None:
    """A resumed run whose --steps (or warm-up) differs from the run it continues re-plans
    the learning-rate schedule for the new total (the old one would have decayed to its
    end value there); say so, since from `start` on the rates then differ from those of
    either run alone."""
    try:
        old = TrainConfig.from_dict(json.loads((out / "train.json").read_text())["train"])
    except (OSError, ValueError, KeyError, TypeError):
        return
    if (old.total_steps, old.warmup_steps) != (tc.total_steps, tc.warmup_steps):
        log(f"note: the learning-rate schedule is re-planned for {tc.total_steps} steps (warm-up {tc.warmup_steps}); "
            f"this run began with {old.total_steps} (warm-up {old.warmup_steps}), so from step {start} on the rates "
            f"follow the new plan (docs/training.md, \"resuming\")")


def _read_log(path: Path, upto: int | None) -> list[dict]:
    """The metrics lines of log.jsonl with step <= upto (a resumed run's checkpoint; the
    rest were not kept), or none without a checkpoint."""
    if upto is None or not path.is_file():
        return []
    recs = []
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
        except ValueError:
            continue
        if isinstance(r, dict) and isinstance(r.get("step"), int) and r["step"] <= upto:
            recs.append(r)
    return recs


def _write_log(path: Path, recs: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))


def plot_loss(history: Sequence[dict], path: str | Path, key: str = "loss_objective",
              size: tuple[int, int] = (640, 360)) -> Path | None:
    """The loss curve (`key` of each record against its "step") as a PNG drawn with
    Pillow; None when there is nothing to draw."""
    from PIL import Image, ImageDraw

    pts = [(float(r["step"]), float(r[key])) for r in history if key in r and np.isfinite(r[key])]
    if not pts:
        return None
    w, h = size
    left, right, top, bottom = 64, 16, 28, 36
    xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    x0, x1 = float(xs.min()), float(max(xs.max(), xs.min() + 1))
    y0, y1 = float(ys.min()), float(ys.max())
    if y1 - y0 < 1e-12:
        y0, y1 = y0 - 0.5, y1 + 0.5
    y0, y1 = y0 - 0.05 * (y1 - y0), y1 + 0.05 * (y1 - y0)

    def px(x, y):
        return (left + (x - x0) / (x1 - x0) * (w - left - right), top + (y1 - y) / (y1 - y0) * (h - top - bottom))

    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    d.rectangle([left, top, w - right, h - bottom], outline=(0, 0, 0))
    for frac in (0.25, 0.5, 0.75):
        y = top + frac * (h - top - bottom)
        d.line([(left, y), (w - right, y)], fill=(225, 225, 225))
    line = [px(x, y) for x, y in pts]
    if len(line) > 1:
        d.line(line, fill=(31, 119, 180), width=2)
    for p in line if len(line) <= 64 else line[-1:]:
        d.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=(31, 119, 180))
    d.text((left, 6), f"{key} (last {ys[-1]:.4g} at step {int(xs[-1])})", fill=(0, 0, 0))
    d.text((4, top), f"{y1:.3g}", fill=(0, 0, 0))
    d.text((4, h - bottom - 10), f"{y0:.3g}", fill=(0, 0, 0))
    d.text((left, h - bottom + 6), f"step {int(x0)}", fill=(0, 0, 0))
    d.text((w - right - 60, h - bottom + 6), f"{int(x1)}", fill=(0, 0, 0))
    path = Path(path)
    img.save(path)
    return path
