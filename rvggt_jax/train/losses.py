"""VGGT's training losses (upstream `training/loss.py`, `MultitaskLoss`), as pure jnp.

Ground truth is a batch dict (see `rvggt_jax.train.data`):

    images       [B, S, 3, H, W] float in [0, 1]
    extrinsics   [B, S, 3, 4]    world-to-camera (OpenCV), frame 0 = identity after
                                 `normalize_example` (upstream normalises the same way)
    intrinsics   [B, S, 3, 3]    pixels of the H x W network input
    depth        [B, S, H, W]    0 where unknown
    world_points [B, S, H, W, 3] the depth unprojected with the cameras
    point_mask   [B, S, H, W]    bool, pixels with valid depth
    tracks       [B, S, N, 2]    optional pixel (x, y) of N points in every frame; the
                                 query points are tracks[:, 0]
    track_vis    [B, S, N]       optional visibility (1 visible) of the tracks

Terms (weights in `LossConfig`; upstream's defaults where upstream has the term):

- camera: for every camera-head iteration i of n, weight gamma^(n-1-i) (gamma 0.6),
  L1 of the pose encoding (absT_quaR_FoV) against the ground truth's encoding, split as
  translation (w 1.0) + quaternion (w 1.0) + field of view (w 0.5); times 5.0.
- depth / point: confidence-weighted regression, per valid pixel
  gamma_c |pred - gt| conf - alpha log(conf) (gamma_c 1, alpha 0.2, |.| the Euclidean
  norm over channels), plus the gradient term: the same confidence weighting of the
  finite differences (x and y) of pred - gt, at 3 scales (strides 1, 2, 4), where both
  neighbours are valid. Upstream filters the largest residuals with a quantile
  (`valid_range` 0.98) and uses a normal-based gradient term for points; neither is
  implemented here (the "grad" term is used for both).
- track (when tracks are given; upstream's VGGT release trains without it, so its form
  is ours): L1 of the final predicted track (the iteration `rvggt_forward` returns)
  against the ground truth over visible points, plus the binary cross-entropy of the
  visibility; times 0.05.

Every mean is over valid elements, guarded against an empty mask (a batch without
depth contributes 0, not NaN).

Gradient accumulation (`TrainConfig.accumulate`) splits a batch into micro-batches whose
losses must add up to the whole batch's: every mean here is a sum over the batch divided
by a count that depends on the data only (valid pixels, elements), so
`record_denominators` takes the whole batch's counts once and, under
`shared_denominators`, each micro-batch's loss divides its sums by those: the
micro-batch losses, their parts and their gradients then sum to the whole batch's
exactly (up to float summation order), whatever the masks of each scene.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from typing import Any, Callable, Iterator, Mapping

import jax
import jax.numpy as jnp

from rvggt_jax.geometry import extri_intri_to_pose_encoding

Batch = Mapping[str, Any]


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Weights of the training loss (upstream's defaults; `track` is ours)."""

    camera: float = 5.0
    depth: float = 1.0
    point: float = 1.0
    track: float = 0.05
    camera_gamma: float = 0.6
    weight_trans: float = 1.0
    weight_rot: float = 1.0
    weight_focal: float = 0.5
    conf_gamma: float = 1.0
    conf_alpha: float = 0.2
    grad_scales: int = 3


class _Denominators:
    """The counts of the means of one loss evaluation, in the order the loss code takes
    them: recorded (`totals` None), or replaced by the given `totals` (a whole batch's)."""

    def __init__(self, totals: list[jax.Array] | None = None):
        self.totals, self.seen = totals, []

    def __call__(self, count: jax.Array) -> jax.Array:
        self.seen.append(count)
        if self.totals is None:
            return count
        if len(self.seen) > len(self.totals):
            raise RuntimeError(f"this loss takes more means than the {len(self.totals)} recorded for the batch "
                               "(a micro-batch's loss must be the same code as the whole batch's)")
        return self.totals[len(self.seen) - 1]


_DENOMINATORS: contextvars.ContextVar[_Denominators | None] = contextvars.ContextVar("rvggt_loss_denominators",
                                                                                     default=None)


def _denominator(count: jax.Array) -> jax.Array:
    hook = _DENOMINATORS.get()
    return count if hook is None else hook(count)


def record_denominators(loss: Callable[[], Any]) -> list[jax.Array]:
    """The count (float32 scalar) of every mean `loss()` takes (e.g. `vggt_loss` of a whole
    batch), in order. They depend on the batch's masks and shapes only, so `loss` may be
    given outputs of the right shapes whose values do not matter (zeros): under `jit`
    XLA drops everything but the counts."""
    token = _DENOMINATORS.set(rec := _Denominators())
    try:
        loss()
    finally:
        _DENOMINATORS.reset(token)
    return [jnp.asarray(c, jnp.float32) for c in rec.seen]


@contextlib.contextmanager
def shared_denominators(totals: list[jax.Array]) -> Iterator[None]:
    """Every mean taken inside divides by the next of `totals` (`record_denominators` of
    the whole batch) instead of its own count: a micro-batch's share of the whole batch's
    loss. Raises if the loss inside takes a different number of means."""
    hook = _Denominators(totals)
    token = _DENOMINATORS.set(hook)
    try:
        yield
    finally:
        _DENOMINATORS.reset(token)
    if len(hook.seen) != len(totals):
        raise RuntimeError(f"the loss took {len(hook.seen)} means where the batch's took {len(totals)}")


def _masked_mean(x: jax.Array, mask: jax.Array) -> jax.Array:
    """mean of x over mask (0 when the mask is empty, never NaN)."""
    m = mask.astype(x.dtype)
    return jnp.sum(x * m) / jnp.maximum(_denominator(jnp.sum(m)), 1.0)


def _mean(x: jax.Array) -> jax.Array:
    """mean of every element of x (the count through `_denominator`, as for masked means)."""
    return jnp.sum(x) / _denominator(jnp.asarray(x.size, x.dtype))


def camera_loss(pose_enc_list: list[jax.Array], extrinsics: jax.Array, intrinsics: jax.Array,
                image_hw: tuple[int, int], cfg: LossConfig) -> dict[str, jax.Array]:
    """pose_enc_list: per-iteration encodings [B, S, 9]; extrinsics [B, S, 3, 4],
    intrinsics [B, S, 3, 3] -> {"loss_camera", "loss_T", "loss_R", "loss_FL"} (scalars,
    the last three of the final iteration, unweighted)."""
    gt = extri_intri_to_pose_encoding(extrinsics, intrinsics, image_hw)
    n = len(pose_enc_list)
    total = jnp.zeros((), jnp.float32)
    parts = {}
    for i, pred in enumerate(pose_enc_list):
        err = jnp.abs(pred - gt)
        lt, lr, lf = _mean(err[..., :3]), _mean(err[..., 3:7]), _mean(err[..., 7:])
        total = total + cfg.camera_gamma ** (n - 1 - i) * (cfg.weight_trans * lt + cfg.weight_rot * lr
                                                           + cfg.weight_focal * lf)
        parts = {"loss_T": lt, "loss_R": lr, "loss_FL": lf}
    return {"loss_camera": total, **parts}


def _gradient_term(diff: jax.Array, conf: jax.Array, mask: jax.Array, cfg: LossConfig) -> jax.Array:
    """Confidence-weighted finite differences of the residual diff [N, H, W, C] over valid
    neighbour pairs, summed over `cfg.grad_scales` strides 1, 2, 4, ..."""
    total = jnp.zeros((), jnp.float32)
    for s in range(cfg.grad_scales):
        step = 2 ** s
        d, c, m = diff[:, ::step, ::step], conf[:, ::step, ::step], mask[:, ::step, ::step]
        for axis in (1, 2):
            n = d.shape[axis]
            if n < 2:
                continue
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(0, n - 1), slice(1, n)
            g = jnp.sqrt(jnp.sum((d[tuple(hi)] - d[tuple(lo)]) ** 2, axis=-1) + 1e-12)  # norm over channels
            cc = c[tuple(hi)]
            mm = m[tuple(hi)] & m[tuple(lo)]
            total = total + _masked_mean(cfg.conf_gamma * g * cc - cfg.conf_alpha * jnp.log(cc), mm)
    return total


def regression_loss(pred: jax.Array, conf: jax.Array, gt: jax.Array, mask: jax.Array, cfg: LossConfig
                    ) -> dict[str, jax.Array]:
    """pred, gt [B, S, H, W, C]; conf [B, S, H, W] (> 1, the heads' 1 + exp); mask
    [B, S, H, W] bool -> {"conf": confidence-weighted term, "reg": plain mean residual
    (reported, not in the objective), "grad": gradient term}."""
    gt = jnp.where(mask[..., None], gt, 0.0)  # no NaN/inf of invalid pixels into the graph
    diff = pred - gt
    # (the epsilon keeps the norm's derivative finite at an exact fit)
    res = jnp.sqrt(jnp.sum(diff * diff, axis=-1) + 1e-12)
    conf_term = _masked_mean(cfg.conf_gamma * res * conf - cfg.conf_alpha * jnp.log(conf), mask)
    flat = (-1,) + pred.shape[2:]
    grad = _gradient_term(diff.reshape(flat), conf.reshape(flat[:-1]), mask.reshape(flat[:-1]), cfg)
    return {"conf": conf_term, "reg": _masked_mean(res, mask), "grad": grad}


def track_loss(tracks: jax.Array, vis: jax.Array, gt_tracks: jax.Array, gt_vis: jax.Array,
               cfg: LossConfig) -> dict[str, jax.Array]:
    """tracks [B, S, N, 2] (the final iteration: what `rvggt_forward` returns), vis
    [B, S, N] probabilities; gt_tracks [B, S, N, 2], gt_vis [B, S, N] in {0, 1}."""
    err = jnp.sum(jnp.abs(tracks - gt_tracks), axis=-1)
    p = jnp.clip(vis, 1e-6, 1 - 1e-6)
    bce = -_mean(gt_vis * jnp.log(p) + (1 - gt_vis) * jnp.log(1 - p))
    return {"loss_track": _masked_mean(err, gt_vis > 0.5), "loss_vis": bce}


def vggt_loss(out: Mapping[str, Any], batch: Batch, cfg: LossConfig = LossConfig()
              ) -> tuple[jax.Array, dict[str, jax.Array]]:
    """(objective, {name: scalar}) from `rvggt_forward`'s outputs `out` and a batch."""
    hw = tuple(batch["images"].shape[-2:])
    parts: dict[str, jax.Array] = {}
    total = jnp.zeros((), jnp.float32)
    if "pose_enc_list" in out and cfg.camera:
        cam = camera_loss(out["pose_enc_list"], batch["extrinsics"], batch["intrinsics"], hw, cfg)
        parts.update(cam)
        total = total + cfg.camera * cam["loss_camera"]
    mask = batch["point_mask"]
    if "depth" in out and cfg.depth:
        d = regression_loss(out["depth"], out["depth_conf"], batch["depth"][..., None], mask, cfg)
        parts.update({"loss_conf_depth": d["conf"], "loss_reg_depth": d["reg"], "loss_grad_depth": d["grad"]})
        total = total + cfg.depth * (d["conf"] + d["grad"])
    if "world_points" in out and cfg.point:
        p = regression_loss(out["world_points"], out["world_points_conf"], batch["world_points"], mask, cfg)
        parts.update({"loss_conf_point": p["conf"], "loss_reg_point": p["reg"], "loss_grad_point": p["grad"]})
        total = total + cfg.point * (p["conf"] + p["grad"])
    if "tracks" in batch and "track" in out and cfg.track:
        t = track_loss(out["track"], out["vis"], batch["tracks"], batch["track_vis"], cfg)
        parts.update(t)
        total = total + cfg.track * (t["loss_track"] + t["loss_vis"])
    parts["loss_objective"] = total
    return total, parts
