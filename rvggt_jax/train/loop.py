"""`rvggt finetune DATA_DIR --out OUT`: fine-tune on a folder of scenes (layout in
`rvggt_jax.train.data`), resumable.

OUT/state/<step>/   Orbax train state (params + optimiser + step); a rerun with the same
                    OUT resumes from the newest one
OUT/train.json      the model and train configs
OUT/model/          the fine-tuned weights (`save_orbax`: `rvggt reconstruct --weights OUT/model`)
OUT/log.jsonl       one line of metrics per logged step
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.forward import InputError
from rvggt_jax.train import data as data_mod
from rvggt_jax.train.step import TrainConfig, init_state, latest_step, make_train_step, restore_state, save_state


@dataclasses.dataclass(frozen=True)
class FinetuneOptions:
    """What `finetune` runs (the CLI's options)."""

    steps: int = 1000
    frames: int = 8
    size: tuple[int, int] = (224, 294)
    batch: int = 1
    accumulate: int = 1  # micro-batches per step: `batch` scenes, `batch / accumulate` at a time
    # over many devices (rvggt_jax.train.sharded): mesh "data" x "frames", frames / frames_per_device
    # devices per scene; fsdp: the train state split over all of them
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


def finetune(data_dir: str | Path, out: str | Path, params: dict, config: VGGTConfig, opts: FinetuneOptions,
             log: Callable[[str], Any] = print) -> Path:
    """Train `params` on the scenes of `data_dir` for `opts.steps` steps (resuming from
    `out` when it holds a train state); returns OUT/model."""
    out = Path(out)
    if opts.steps < 1 or opts.frames < 1 or opts.batch < 1:
        raise InputError(f"steps, frames and batch must be >= 1; got {opts.steps}, {opts.frames}, {opts.batch}")
    if opts.accumulate < 1 or opts.batch % opts.accumulate:
        divisors = [k for k in range(1, opts.batch + 1) if opts.batch % k == 0]
        raise InputError(f"--accumulate {opts.accumulate} must divide --batch {opts.batch} (micro-batches of "
                         f"batch / accumulate scenes): --batch {opts.batch} takes --accumulate in {divisors}")
    layout = None
    if opts.devices > 1 or opts.fsdp or opts.frames_per_device is not None:  # (checked before reading data)
        from rvggt_jax.train.sharded import train_layout

        layout = train_layout(opts.devices, opts.batch, opts.frames, opts.frames_per_device,
                              accumulate=opts.accumulate, fsdp=opts.fsdp)
    scenes = data_mod.folder_scenes(data_dir)
    usable = [s for s in scenes if len(s) >= opts.frames]
    if not usable:
        raise InputError(f"no scene in {data_dir} has {opts.frames} frames (--frames); they have "
                         f"{sorted(len(s) for s in scenes)}")
    if opts.preset:
        config = config.with_compression(opts.preset)
    config = config.with_dtype(opts.dtype).with_remat(opts.remat)
    warmup = opts.warmup_steps if opts.warmup_steps is not None else min(500, opts.steps // 10)
    tc = TrainConfig(learning_rate=opts.learning_rate, warmup_steps=warmup, total_steps=opts.steps,
                     train=opts.train, accumulate=opts.accumulate).validate()

    state = init_state(params, tc)
    start = latest_step(out)
    if start is not None:
        state = restore_state(out, state)
        log(f"resuming from step {start} in {out}")
    step_fn, place = make_train_step(config, tc), (lambda b: b)
    if layout is not None:
        from rvggt_jax.train import sharded as multi

        mesh = multi.train_mesh(layout)
        step_fn = multi.make_sharded_train_step(config, tc, mesh, fsdp=layout.fsdp)
        state, place = multi.place_state(state, mesh, layout.fsdp), (lambda b: multi.place_batch(b, mesh))
        log(f"training on {layout.describe()}")
    rng = np.random.default_rng(opts.seed + int(state.step))  # a resumed run draws new batches

    def example(r):
        return data_mod.scene_example(usable[int(r.integers(len(usable)))], opts.frames, opts.size, r)

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(out / "log.jsonl", "a") as logf:
        for i in range(int(state.step), opts.steps):
            batch = data_mod.stack([example(rng) for _ in range(opts.batch)])
            state, metrics = step_fn(state, place(batch))
            if (i + 1) % opts.log_every == 0 or i + 1 == opts.steps or i == 0:
                m = {k: float(v) for k, v in jax.device_get(metrics).items()}
                logf.write(json.dumps({"step": i + 1, **m}) + "\n")
                logf.flush()
                log(f"step {i + 1}/{opts.steps}  loss {m['loss_objective']:.4f}  lr {m['lr']:.2e}  "
                    f"grad norm {m['grad_norm']:.3f}  ({time.perf_counter() - t0:.0f} s)")
            if (i + 1) % opts.save_every == 0 and i + 1 < opts.steps:
                save_state(state, out, model_config=config, train_config=tc)
    save_state(state, out, model_config=config, train_config=tc)

    from rvggt_jax.weights.checkpoint import save_orbax

    model_dir = save_orbax(jax.device_get(state.params), config, out / "model", overwrite=True)
    log(f"fine-tuned weights: {model_dir} (rvggt reconstruct --weights {model_dir})")
    return model_dir
