"""Fine-tuning VGGT with optax: losses, data, the jitted train step, checkpoints.

    from rvggt_jax import train
    tc = train.TrainConfig(learning_rate=1e-4, warmup_steps=50, total_steps=1000, train="heads")
    state = train.init_state(params, tc)
    step = train.make_train_step(config, tc)
    batch = train.stack([train.synthetic_example(8, (224, 294), seed=0)])
    state, metrics = step(state, batch)

Over many devices (mesh "data" x "frames", FSDP): `train.sharded` (`make_sharded_train_step`).
See docs/training.md. `rvggt finetune DATA_DIR --out DIR` runs `rvggt_jax.train.finetune`
(module `rvggt_jax.train.loop`) on any dataset format `rvggt_jax.train.open_scenes` reads,
with a random frame count per step in a few compiled buckets (`rvggt_jax.train.data`).
Names resolve on first use (building the CLI parser imports no JAX).
"""

import importlib

_LAZY = {
    **{n: "rvggt_jax.train.data" for n in ("BatchStream", "TRAIN_FORMATS", "batches", "default_buckets",
                                           "detect_format", "draw_batch_plan", "folder_scenes", "frame_plan",
                                           "make_example", "normalize_example", "open_scenes", "scene_example",
                                           "stack", "step_batch", "synthetic_example")},
    **{n: "rvggt_jax.train.losses" for n in ("LossConfig", "camera_loss", "regression_loss", "track_loss",
                                             "vggt_loss")},
    **{n: "rvggt_jax.train.step" for n in ("TrainConfig", "TrainState", "init_state", "latest_step", "loss_fn",
                                           "make_optimizer", "make_train_step", "param_labels", "restore_state",
                                           "save_state", "schedule")},
    **{n: "rvggt_jax.train.loop" for n in ("BucketedStep", "FinetuneOptions", "device_layout", "finetune", "load_model",
                                           "plot_loss")},
    **{n: "rvggt_jax.train.sharded" for n in ("TrainLayout", "make_sharded_train_step", "place_batch", "place_state",
                                              "train_layout", "train_mesh")},
}
_SUBMODULES = ("data", "losses", "step", "loop", "sharded", "cli")
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in _SUBMODULES:
        return importlib.import_module(f"rvggt_jax.train.{name}")
    raise AttributeError(f"module 'rvggt_jax.train' has no attribute {name!r}")
