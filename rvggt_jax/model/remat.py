"""Rematerialisation for training: which parts of the forward are a `jax.checkpoint` under
`VGGTConfig.remat`, and what each keeps for the backward pass.

    "none"    nothing is a checkpoint: reverse mode keeps every intermediate it needs.
    "layers"  each aggregator layer (frame + global block) and each DINO block but the
              last is a checkpoint that keeps its inputs alone (`remat=True` before the
              policies).
    "full"    "layers", and the DINOv2 patch embed as a whole (its blocks' inputs are
              recomputed in the backward pass too; VGGT-Omega's "required" checkpoint),
              and each frame group of the DPT heads. A step then keeps the images, the
              input of each aggregator layer, the kept layers the heads read and the
              camera head's small tensors: nothing per frame of the heads' feature maps
              (at 518 x 518 each frame's are ~1 GiB per head). True means "full".
    "dots"    "full", each aggregator layer and DINO block keeping its matmul outputs
              (`jax.checkpoint_policies.dots_with_no_batch_dims_saveable`: the
              projections and MLP, not attention's batched products): fewer FLOPs
              recomputed, about 0.8 GiB more per block at 24 frames of 518 x 518
              (VGGT-1B, everything trained, H200 plan: 84.8 GiB, "full" 28.8).

Every checkpoint also keeps the scalar zeros `ops.ordering.ordered_after` orders work
with (named `ORDER_NAME`): recomputed, each would need the array it was made from, and
the aggregator's layers would keep their kept-layer buffer (258 MB at 24 frames of
518 x 518) per layer.

Frozen parts (`TrainConfig.train`) keep nothing whatever the policy: the train step
stops their gradients, so no tangent reaches them and reverse mode saves nothing of
their forward but the outputs a trained part reads (the kept layers, for the heads).
Values are the same under every policy (the recomputation is the same computation).
"""

from __future__ import annotations

from typing import Callable

import jax

from rvggt_jax.config import REMAT_POLICIES, VGGTConfig
from rvggt_jax.ops.ordering import ORDER_NAME

__all__ = ["PARTS", "checkpoint"]

# what a policy checkpoints: "block" an aggregator layer or DINO block, "patch_embed" the
# DINOv2 forward as a whole, "head" one frame group of a DPT head
PARTS = ("block", "patch_embed", "head")
_CHECKPOINTED = {"none": (), "layers": ("block",), "full": PARTS, "dots": PARTS}


def checkpoint(fn: Callable, config: VGGTConfig | str, part: str) -> Callable:
    """`fn` as `config.remat` runs `part` (one of `PARTS`) in a training step: a
    `jax.checkpoint` of it (with the policy's saved values), or `fn` itself."""
    policy = config if isinstance(config, str) else config.remat
    if policy not in REMAT_POLICIES:
        raise ValueError(f"remat must be one of {REMAT_POLICIES}; got {policy!r}")
    if part not in PARTS:
        raise ValueError(f"part must be one of {PARTS}; got {part!r}")
    if part not in _CHECKPOINTED[policy]:
        return fn
    saved = jax.checkpoint_policies.save_only_these_names(ORDER_NAME)
    if policy == "dots" and part == "block":
        saved = jax.checkpoint_policies.save_from_both_policies(
            jax.checkpoint_policies.dots_with_no_batch_dims_saveable, saved)
    return jax.checkpoint(fn, policy=saved)
