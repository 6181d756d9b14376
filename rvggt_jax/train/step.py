"""Optimiser, train state, the jitted train step and Orbax checkpoints of the state.

    tc = TrainConfig(learning_rate=1e-4, warmup_steps=100, total_steps=2000, train="heads")
    state = init_state(params, tc)
    step = make_train_step(config, tc)                 # one jax.jit: forward, loss, grad, AdamW
    state, metrics = step(state, batch)                # batch: see rvggt_jax.train.losses
    save_state(state, "ckpt/", model_config=config, train_config=tc)
    state = restore_state("ckpt/", init_state(params, tc))   # resumes exactly

Gradient accumulation: `TrainConfig(accumulate=K)` splits each batch of B scenes into K
micro-batches of B / K (a `lax.scan`: one micro-batch's activations at a time) whose
gradients add up to the whole batch's, every loss mean divided by the whole batch's
count (`losses.shared_denominators`): one update, the same as the step on all B scenes
at once (to float summation order), whatever the scenes' masks.

The optimiser: global-norm clipping, then AdamW (decoupled weight decay on kernels,
i.e. leaves of rank >= 2, not on biases, norms, tokens or LayerScale) with a linear
warm-up from 0 to `learning_rate` over `warmup_steps` and a cosine decay to
`learning_rate * final_lr_ratio` at `total_steps`. Frozen parameters
(`TrainConfig.train`) get `optax.set_to_zero` through `optax.multi_transform`, their
gradients are never formed (stop_gradient inside the differentiated function,
`trainable_loss`: no tangent reaches them, so reverse mode keeps nothing of the work only
they feed) and they are not counted in the clipping norm.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp
import optax

from rvggt_jax.config import VGGTConfig
from rvggt_jax.train.losses import LossConfig, record_denominators, shared_denominators, vggt_loss

TRAIN, FROZEN = "train", "frozen"
HEADS = ("camera_head", "depth_head", "point_head", "track_head")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimiser and schedule (frozen, hashable: a static argument of the train step).

    train: what is trained: "all", "heads" (everything but the aggregator), or a tuple
    of path prefixes of the parameter tree ("depth_head", "aggregator/global_blocks");
    the rest is frozen.
    accumulate: micro-batches per step (gradient accumulation); it must divide the batch."""

    learning_rate: float = 1e-4
    warmup_steps: int = 100
    total_steps: int = 10_000
    final_lr_ratio: float = 0.0
    weight_decay: float = 0.05
    b1: float = 0.9
    b2: float = 0.999
    clip_norm: float = 1.0
    train: str | tuple[str, ...] = "all"
    accumulate: int = 1
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)

    def validate(self) -> "TrainConfig":
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0; got {self.learning_rate}")
        if self.warmup_steps < 0 or self.total_steps < 1:
            raise ValueError(f"need warmup_steps >= 0 and total_steps >= 1; got {self.warmup_steps}, "
                             f"{self.total_steps}")
        if not self.clip_norm > 0:
            raise ValueError(f"clip_norm must be > 0; got {self.clip_norm}")
        if not (isinstance(self.accumulate, int) and self.accumulate >= 1):
            raise ValueError(f"accumulate (micro-batches per step) must be an integer >= 1; got {self.accumulate!r}")
        if isinstance(self.train, str) and self.train not in ("all", "heads"):
            raise ValueError(f"train must be 'all', 'heads' or a tuple of parameter path prefixes; got {self.train!r}")
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        d["loss"] = LossConfig(**d.get("loss", {}))
        if isinstance(d.get("train"), list):
            d["train"] = tuple(d["train"])
        return cls(**d).validate()


@flax.struct.dataclass
class TrainState:
    """step (int32 scalar), params (the converter's tree), opt_state (optax)."""

    step: jax.Array
    params: Any
    opt_state: Any


def _path_str(path) -> str:
    return "/".join(str(getattr(k, "key", getattr(k, "name", k))) for k in path)


def param_labels(params: Any, train: str | tuple[str, ...]) -> Any:
    """A tree like `params` of "train" / "frozen" labels for `TrainConfig.train`.
    Raises when a prefix matches no parameter (a typo would silently freeze everything)."""
    if train == "all":
        prefixes: tuple[str, ...] = ("",)
    elif train == "heads":
        prefixes = tuple(h for h in HEADS if h in params)
    else:
        prefixes = tuple(p.strip("/") for p in train)
    paths = [_path_str(p) for p, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
    for pre in prefixes:
        if pre and not any(p == pre or p.startswith(pre + "/") for p in paths):
            raise ValueError(f"train prefix {pre!r} matches no parameter; nearest parameter paths: "
                             f"{', '.join(nearest_paths(pre, paths)) or '(none)'} (top level: {sorted(params)})")

    def label(path, _):
        s = _path_str(path)
        return TRAIN if any(not pre or s == pre or s.startswith(pre + "/") for pre in prefixes) else FROZEN

    return jax.tree_util.tree_map_with_path(label, params)


def nearest_paths(prefix: str, paths: list[str], n: int = 5) -> list[str]:
    """The `n` parameter paths or path prefixes ('/'-joined, e.g. "aggregator/frame_blocks")
    closest to `prefix` (difflib's ratio), for an error on a prefix that matches nothing.
    A prefix with as many '/'-separated parts as `prefix` is compared first (a typo in a
    short prefix finds the short prefix it meant, not a long leaf path)."""
    import difflib

    cands = {"/".join(p.split("/")[:k]) for p in paths for k in range(1, p.count("/") + 2)}
    depth = prefix.count("/")
    same = sorted(c for c in cands if c.count("/") == depth)
    near = difflib.get_close_matches(prefix, same, n=n, cutoff=0.5)
    rest = difflib.get_close_matches(prefix, sorted(cands - set(near)), n=n, cutoff=0.5)
    return (near + rest)[:n]


def schedule(tc: TrainConfig) -> optax.Schedule:
    """Linear warm-up to the peak, cosine decay to `final_lr_ratio` of it at total_steps."""
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=tc.learning_rate, warmup_steps=tc.warmup_steps,
        decay_steps=max(tc.total_steps, tc.warmup_steps + 1), end_value=tc.learning_rate * tc.final_lr_ratio)


def make_optimizer(tc: TrainConfig, params: Any) -> optax.GradientTransformation:
    """clip_by_global_norm + AdamW for the trained leaves, set_to_zero for the frozen."""
    tc.validate()
    decay_mask = jax.tree.map(lambda p: jnp.ndim(p) >= 2, params)
    trained = optax.chain(
        optax.clip_by_global_norm(tc.clip_norm),
        optax.adamw(schedule(tc), b1=tc.b1, b2=tc.b2, weight_decay=tc.weight_decay, mask=decay_mask))
    return optax.multi_transform({TRAIN: trained, FROZEN: optax.set_to_zero()}, param_labels(params, tc.train))


def init_state(params: Any, tc: TrainConfig) -> TrainState:
    """A fresh train state (step 0) for `params`."""
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=make_optimizer(tc, params).init(params))


def _query_points(batch: dict) -> jax.Array | None:
    return batch["tracks"][:, 0] if "tracks" in batch else None


# (params, images [B, S, 3, H, W], query points [B, N, 2] or None) -> `rvggt_forward`'s
# outputs: the forward a train step differentiates (None: `rvggt_forward` on one device;
# `rvggt_jax.train.sharded` passes one split over a mesh)
Forward = Callable[[Any, jax.Array, "jax.Array | None"], dict]


def loss_fn(params: Any, batch: dict, config: VGGTConfig, loss_cfg: LossConfig, forward: Forward | None = None
            ) -> tuple[jax.Array, dict]:
    """(objective, parts) of `rvggt_forward(params, batch["images"], config)` (or of
    `forward(params, images, query_points)`) on a batch."""
    from rvggt_jax.model.forward import rvggt_forward

    if forward is None:
        out = rvggt_forward(params, batch["images"], config, _query_points(batch))
    else:
        out = forward(params, batch["images"], _query_points(batch))
    return vggt_loss(out, batch, loss_cfg)


def frozen_as_constants(params: Any, labels: Any) -> Any:
    """`params` with every frozen leaf (label FROZEN) behind `stop_gradient`. Applied
    inside the differentiated function, their tangents are symbolic zeros: reverse mode
    neither computes nor keeps anything for the work that only they feed (a frozen
    aggregator runs as a plain forward; only its outputs the trained heads read are kept).
    Outside it, stop_gradient would not mark them (a differentiated argument is a tracer),
    the whole forward would be linearised and its residuals left to XLA's dead-code
    elimination, which XLA:CPU does not finish (its plan of the frozen aggregator kept
    each attention block's K and V: 39 GiB at 48 frames of 518 x 518)."""
    return jax.tree.map(lambda p, lab: p if lab == TRAIN else jax.lax.stop_gradient(p), params, labels)


def trainable_loss(params: Any, batch: dict, config: VGGTConfig, tc: TrainConfig, forward: Forward | None = None
                   ) -> tuple[jax.Array, dict]:
    """`loss_fn` with the parameters `tc.train` freezes as constants (`frozen_as_constants`):
    the function the train step differentiates."""
    return loss_fn(frozen_as_constants(params, param_labels(params, tc.train)), batch, config, tc.loss, forward)


def divisors(n: int) -> list[int]:
    """The divisors of `n`, ascending: what an error offers when a count must divide `n`."""
    return [k for k in range(1, n + 1) if n % k == 0]


def micro_batches(batch: dict, accumulate: int) -> dict:
    """Every leaf [B, ...] -> [accumulate, B / accumulate, ...] (consecutive scenes per
    micro-batch). A ValueError when `accumulate` does not divide B, naming the ones that do."""
    b = batch["images"].shape[0]
    if b % accumulate:
        raise ValueError(f"accumulate={accumulate} does not divide the batch of {b} scenes: use accumulate in "
                         f"{divisors(b)}, or a batch that is a multiple of {accumulate}")
    return jax.tree.map(lambda x: x.reshape((accumulate, b // accumulate) + x.shape[1:]), batch)


def accumulated_value_and_grad(params: Any, batch: dict, config: VGGTConfig, tc: TrainConfig,
                               forward: Forward | None = None) -> tuple[tuple[jax.Array, dict], Any]:
    """`jax.value_and_grad(loss_fn, has_aux=True)(params, batch, ...)` over
    `tc.accumulate` micro-batches: a `lax.scan` holding one micro-batch's forward and
    backward at a time, gradients summed in float32 (returned in the parameters'
    dtypes). Each micro-batch's loss divides by the whole batch's counts (its share of the
    whole loss, `losses.shared_denominators`), so the sums are the whole batch's
    objective, parts and gradient. The parameters `tc.train` freezes are constants
    (`trainable_loss`): their gradients are zeros."""
    from rvggt_jax.model.forward import rvggt_forward

    micro = micro_batches(batch, tc.accumulate)
    # the whole batch's counts: its loss on outputs of the right shapes (their values do
    # not matter and XLA drops them; the forward is only traced, for its shapes)
    shapes = jax.eval_shape(lambda p, b: rvggt_forward(p, b["images"], config, _query_points(b)), params, batch)
    totals = record_denominators(lambda: vggt_loss(jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes),
                                                   batch, tc.loss))

    def one(acc, mb):
        with shared_denominators(totals):
            (loss, parts), grads = jax.value_and_grad(trainable_loss, has_aux=True)(params, mb, config, tc, forward)
        return jax.tree.map(lambda a, x: a + x.astype(jnp.float32), acc, (loss, parts, grads)), None

    # float32 sums of the loss, its parts (shapes: a forward trace) and the gradient (the params')
    loss_parts = jax.eval_shape(lambda p, b: loss_fn(p, b, config, tc.loss), params,
                                jax.tree.map(lambda x: x[0], micro))
    zero = jax.tree.map(lambda a: jnp.zeros(jnp.shape(a), jnp.float32), (*loss_parts, params))
    (loss, parts, grads), _ = jax.lax.scan(one, zero, micro)
    grads = jax.tree.map(lambda g, p: g.astype(jnp.result_type(p)), grads, params)
    return (loss, parts), grads


def make_train_step(config: VGGTConfig, tc: TrainConfig, *, donate: bool = True
                    ) -> Callable[[TrainState, dict], tuple[TrainState, dict]]:
    """`step(state, batch) -> (state, metrics)`, one `jax.jit` (forward, loss, gradient,
    clipping, AdamW); with `tc.accumulate` = K, the gradient of the batch's K
    micro-batches, one at a time (`accumulated_value_and_grad`), one update. metrics:
    every loss part (of the whole batch), "grad_norm" (trained leaves, before
    clipping) and "lr" (the rate this step used). `donate`: the input state's buffers are
    reused for the output (do not use a state after passing it). Over many devices:
    `rvggt_jax.train.sharded.make_sharded_train_step`."""
    return jax.jit(train_step_fn(config, tc), donate_argnums=(0,) if donate else ())


def train_step_fn(config: VGGTConfig, tc: TrainConfig, forward: Forward | None = None
                  ) -> Callable[[TrainState, dict], tuple[TrainState, dict]]:
    """The function `make_train_step` jits (not jitted), its forward `forward` (default
    `rvggt_forward`)."""
    tc.validate()
    config.validate()

    def step(state: TrainState, batch: dict) -> tuple[TrainState, dict]:
        labels = param_labels(state.params, tc.train)
        # frozen leaves as constants inside the differentiated function (`trainable_loss`):
        # their cotangents, and any backward pass or residual that only they need (the
        # aggregator's when training heads), are never formed
        if tc.accumulate == 1:
            (loss, parts), grads = jax.value_and_grad(trainable_loss, has_aux=True)(state.params, batch, config, tc,
                                                                                    forward)
        else:
            (loss, parts), grads = accumulated_value_and_grad(state.params, batch, config, tc, forward)
        trained = jax.tree.map(lambda g, lab: g if lab == TRAIN else jnp.zeros((), g.dtype), grads, labels)
        tx = make_optimizer(tc, state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        grad_norm = jnp.sqrt(sum(jnp.sum(jnp.square(g.astype(jnp.float32))) for g in jax.tree.leaves(trained)))
        metrics = dict(parts, grad_norm=grad_norm, lr=schedule(tc)(state.step))
        return TrainState(step=state.step + 1, params=params, opt_state=opt_state), metrics

    return step


# ---------------------------------------------------------------------------------------
# checkpoints
# ---------------------------------------------------------------------------------------

STATE_DIR = "state"
META_NAME = "train.json"


def save_state(state: TrainState, directory: str | Path, *, model_config: VGGTConfig | None = None,
               train_config: TrainConfig | None = None, keep: int = 2) -> Path:
    """Write `state` as Orbax checkpoint `directory/state/<step>/` (the `keep` newest are
    kept) and, when given, the configs to `directory/train.json`. Returns the step's
    folder."""
    import orbax.checkpoint as ocp

    from rvggt_jax.weights.checkpoint import _quiet_absl

    directory = Path(directory).absolute()
    directory.mkdir(parents=True, exist_ok=True)
    step = int(jax.device_get(state.step))
    mgr = ocp.CheckpointManager(directory / STATE_DIR, options=ocp.CheckpointManagerOptions(max_to_keep=keep))
    try:
        with _quiet_absl():
            mgr.save(step, args=ocp.args.StandardSave(state), force=True)
            mgr.wait_until_finished()
    finally:
        mgr.close()
    if model_config is not None or train_config is not None:
        meta = {}
        if model_config is not None:
            meta["model"] = model_config.to_dict()
        if train_config is not None:
            meta["train"] = train_config.to_dict()
        (directory / META_NAME).write_text(json.dumps(meta, indent=1))
    return directory / STATE_DIR / str(step)


def latest_step(directory: str | Path) -> int | None:
    """The newest saved step under `directory`, or None."""
    import orbax.checkpoint as ocp

    d = Path(directory).absolute() / STATE_DIR
    if not d.is_dir():
        return None
    mgr = ocp.CheckpointManager(d)
    try:
        return mgr.latest_step()
    finally:
        mgr.close()


def restore_state(directory: str | Path, like: TrainState, step: int | None = None) -> TrainState:
    """The state saved under `directory` (newest step, or `step`), restored into the
    structure, shapes and dtypes of `like` (e.g. `init_state(params, tc)`, or its
    `jax.eval_shape`)."""
    import orbax.checkpoint as ocp

    from rvggt_jax.weights.checkpoint import _quiet_absl

    d = Path(directory).absolute() / STATE_DIR
    mgr = ocp.CheckpointManager(d)
    try:
        step = mgr.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no train-state checkpoint under {d}")
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)), like)
        with _quiet_absl():
            return mgr.restore(step, args=ocp.args.StandardRestore(abstract))
    finally:
        mgr.close()
