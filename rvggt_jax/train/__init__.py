"""Fine-tuning VGGT with optax: losses, data, the jitted train step, checkpoints.

    from rvggt_jax import train
    tc = train.TrainConfig(learning_rate=1e-4, warmup_steps=50, total_steps=1000, train="heads")
    state = train.init_state(params, tc)
    step = train.make_train_step(config, tc)
    for batch in train.batches(lambda rng: train.synthetic_example(8, (224, 294), int(rng.integers(1 << 30))), 1):
        state, metrics = step(state, batch)

See docs/training.md. `rvggt finetune DATA_DIR --out DIR` runs `rvggt_jax.train.finetune`.
"""

from rvggt_jax.train.data import (batches, folder_scenes, make_example, normalize_example, scene_example, stack,
                                  synthetic_example)
from rvggt_jax.train.losses import LossConfig, camera_loss, regression_loss, track_loss, vggt_loss
from rvggt_jax.train.step import (TrainConfig, TrainState, init_state, latest_step, loss_fn, make_optimizer,
                                  make_train_step, param_labels, restore_state, save_state, schedule)

__all__ = ["LossConfig", "TrainConfig", "TrainState", "batches", "camera_loss", "folder_scenes", "init_state",
           "latest_step", "loss_fn", "make_example", "make_optimizer", "make_train_step", "normalize_example",
           "param_labels", "regression_loss", "restore_state", "save_state", "scene_example", "schedule", "stack",
           "synthetic_example", "track_loss", "vggt_loss"]
