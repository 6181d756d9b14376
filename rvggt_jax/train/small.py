"""`rvggt train-small --out DIR`: the small VGGT shipped as "rvggt-small", trained from
scratch on procedural scenes (`rvggt_jax.train.procedural`) by the project's own loop
(`rvggt_jax.train.loop.run_training`). Fixed seed, resumable exactly (rerun the same
command: it continues from OUT/state's newest step and draws the same batches).

    OUT/state/<step>/  train state          OUT/log.jsonl, OUT/loss.png   metrics
    OUT/model/         the trained weights; config.json records "train_image_size"

`SmallRecipe` holds every choice of the shipped run; the defaults are that run
(rvggt_jax/examples_data/rvggt_small/README.md). `ship(OUT/model)` copies a finished model into the
package folder that `load_pretrained("rvggt-small")` reads.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any, Callable

from rvggt_jax.config import VGGTConfig
from rvggt_jax.weights.pretrained import BUNDLED, train_image_size

SHIPPED_DIR = BUNDLED["rvggt-small"]
"""The shipped model's folder (Orbax params + config.json + model card): "rvggt-small"."""


@dataclasses.dataclass(frozen=True)
class SmallRecipe:
    """The shipped run: `VGGTConfig.rvggt_small()` at `size`, `batch` procedural scenes of
    2..8 frames (buckets 2, 4, 8) a step, AdamW at `learning_rate` (warm-up, cosine to
    `final_lr_ratio` x), upstream's loss weights, `tracks` exact ground-truth tracks a
    scene for the track head."""

    steps: int = 3200
    size: tuple[int, int] = (84, 112)
    frames: tuple[int, int] = (2, 8)
    buckets: tuple[int, ...] = (2, 4, 8)
    batch: int = 1
    learning_rate: float = 3e-4
    warmup_steps: int = 250
    final_lr_ratio: float = 0.02
    tracks: int = 64
    seed: int = 0
    save_every: int = 250
    log_every: int = 25
    # the LayerScale of the frame, global and camera-trunk blocks at step 0 (None: upstream's
    # 0.01, see `with_layer_scale`)
    layer_scale: float | None = None


def train_small(out: str | Path, recipe: SmallRecipe = SmallRecipe(), *, stop_at: int | None = None,
                log: Callable[[str], Any] = print, progress: bool = True) -> Path:
    """Train (or resume) the small model into `out`; returns OUT/model when `recipe.steps`
    are done, else the newest OUT/state step."""
    import jax

    import rvggt_jax
    from rvggt_jax.train.loop import FinetuneOptions, run_training
    from rvggt_jax.train.procedural import TRAIN_SEED_BASE, procedural_batch
    from rvggt_jax.train.step import TrainConfig, latest_step

    from rvggt_jax.train import data as data_mod

    out = Path(out)
    data_mod._check_size(recipe.size)  # bad settings fail before anything is built
    data_mod.frame_plan(recipe.frames, recipe.buckets)
    config = VGGTConfig.rvggt_small()
    init = lambda: with_layer_scale(rvggt_jax.init_params(config, recipe.seed), recipe.layer_scale)  # noqa: E731
    # a resumed run reads every parameter from OUT/state: their shapes are enough
    params = jax.eval_shape(init) if latest_step(out) is not None else init()
    tc = TrainConfig(learning_rate=recipe.learning_rate, warmup_steps=recipe.warmup_steps, total_steps=recipe.steps,
                     final_lr_ratio=recipe.final_lr_ratio).validate()
    opts = FinetuneOptions(steps=recipe.steps, frames=recipe.frames, size=recipe.size, batch=recipe.batch,
                           learning_rate=recipe.learning_rate, warmup_steps=recipe.warmup_steps,
                           save_every=recipe.save_every, log_every=recipe.log_every, seed=recipe.seed,
                           buckets=recipe.buckets, stop_at=stop_at)

    def make(i: int) -> dict:
        return procedural_batch(i, recipe.seed, recipe.batch, recipe.frames, recipe.size, recipe.buckets,
                                recipe.tracks)

    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.json").write_text(json.dumps(dataclasses.asdict(recipe), indent=1))
    result = run_training(out, params, config, tc, opts, make, recipe.buckets,
                          f"procedural scenes (seeds from {TRAIN_SEED_BASE}), {recipe.batch} a step, at "
                          f"{recipe.size[0]}x{recipe.size[1]}", log=log, progress=progress, desc="train-small")
    if (result / "config.json").is_file():
        record_train_size(result, recipe.size)
    return result


def with_layer_scale(params: dict, value: float | None) -> dict:
    """`params` with every LayerScale gamma outside the DINO patch embed (the frame, global
    and camera-trunk blocks) set to `value`; None returns `params` unchanged.

    Upstream starts these at 0.01 because its aggregator starts from a trained DINO and
    trains for days. From scratch on a CPU budget they barely move (rvggt-small's ended at
    0.007-0.010 after 3200 steps), so each block adds about 1% to the token stream; this
    starts them at full strength instead. It is not what limits rvggt-small's cameras:
    see its model card, "What limits the cameras" (`benchmarks/camera_probe.py`).
    """
    if value is None:
        return params
    if not value > 0:
        raise ValueError(f"layer_scale must be > 0; got {value}")
    import jax
    import jax.numpy as jnp

    def set_gamma(path, leaf):
        keys = [getattr(k, "key", None) for k in path]
        if keys[-1] == "gamma" and "patch_embed" not in keys:
            return jnp.full_like(leaf, value)
        return leaf

    return jax.tree_util.tree_map_with_path(set_gamma, params)


def record_train_size(model_dir: str | Path, size: tuple[int, int]) -> None:
    """Add `"train_image_size": [H, W]` to MODEL_DIR/config.json."""
    path = Path(model_dir) / "config.json"
    cfg = json.loads(path.read_text())
    cfg["train_image_size"] = [int(size[0]), int(size[1])]
    path.write_text(json.dumps(cfg, indent=1))


def ship(model_dir: str | Path, dst: str | Path = SHIPPED_DIR) -> Path:
    """Store a trained model folder in the package as "rvggt-small": its weights rounded to
    float16 (half the size: the package ships at most 20 MB; they load as float32, and the
    shipped model's metrics are measured on these rounded weights), its config.json (with
    "train_image_size"). The model card already in `dst` is kept."""
    import jax
    import numpy as np

    from rvggt_jax.weights.checkpoint import load_checkpoint, save_orbax

    src, dst = Path(model_dir), Path(dst)
    if not (src / "config.json").is_file() or not (src / "params").is_dir():
        raise FileNotFoundError(f"{src} is not a trained model folder (params/ and config.json)")
    params, config = load_checkpoint(src, device_put=False)
    half = jax.tree.map(lambda x: np.asarray(x, np.float16), params)
    for stale in ("params", "digests.json"):
        if (dst / stale).is_dir():
            shutil.rmtree(dst / stale)
        elif (dst / stale).exists():
            (dst / stale).unlink()
    save_orbax(half, config, dst, overwrite=True)
    size = train_image_size(src)
    if size is not None:
        record_train_size(dst, size)
    return dst
