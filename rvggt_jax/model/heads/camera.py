"""Camera head: iterative refinement of a 9-d pose encoding from each frame's camera token.

Parameters are the `camera_head` subtree of the converted state dict (see
docs/conventions.md): `token_norm`, `trunk.{i}` (transformer blocks without RoPE or
qk-norm, with LayerScale), `trunk_norm`, `empty_pose_tokens [1, 1, 9]`, `embed_pose`,
`poseLN_modulation.1` (the Linear after the SiLU), `pose_branch.{fc1, fc2}`.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp

from rvggt_jax.model import layers
from rvggt_jax.config import CameraHeadConfig
from rvggt_jax.model.params import Params


# The only LayerNorm of the head that is not torch's default (1e-5): the affine-free adaLN.
ADALN_EPS = 1e-6


def activate_pose(pose_enc: jax.Array, trans_act: str = "linear", quat_act: str = "linear",
                  fl_act: str = "linear") -> jax.Array:
    """Per-part activation of a raw encoding [..., 9]: translation [:3], quaternion [3:7],
    field of view [7:] (focal length in other encodings)."""
    return jnp.concatenate([
        pose_activation(pose_enc[..., :3], trans_act),
        pose_activation(pose_enc[..., 3:7], quat_act),
        pose_activation(pose_enc[..., 7:], fl_act),
    ], axis=-1)


def pose_activation(x: jax.Array, act: str) -> jax.Array:
    """'linear', 'inv_log' (sign(x) * (exp|x| - 1)), 'exp' or 'relu', elementwise."""
    if act == "linear":
        return x
    if act == "inv_log":
        return inverse_log_transform(x)
    if act == "exp":
        return jnp.exp(x)
    if act == "relu":
        return jax.nn.relu(x)
    raise ValueError(f"unknown pose activation {act!r}")


def inverse_log_transform(y: jax.Array) -> jax.Array:
    """sign(y) * (exp(|y|) - 1), elementwise; expm1 keeps small |y| accurate."""
    return jnp.sign(y) * jnp.expm1(jnp.abs(y))


def _trunk(params: Params, x: jax.Array, num_heads: int) -> jax.Array:
    """The trunk attends across the S frames of each batch element: x [B, S, C]."""
    return layers.block_stack(params, range(len(params)), x, None, layers.BlockConfig(num_heads))


def _refine(params: Params, tokens: jax.Array, raw_pose: jax.Array, num_heads: int) -> jax.Array:
    """One refinement step: the raw (pre-activation) encoding [B, S, 9] conditions the
    normalised camera tokens [B, S, C] through adaLN; returns the raw delta [B, S, 9]."""
    cond = layers.linear(params["embed_pose"], raw_pose)
    shift, scale, gate = jnp.split(layers.linear(params["poseLN_modulation"]["1"], jax.nn.silu(cond)), 3, axis=-1)
    modulated = layers.layer_norm(None, tokens, eps=ADALN_EPS) * (1 + scale) + shift
    x = _trunk(params["trunk"], gate * modulated + tokens, num_heads)
    return layers.mlp(params["pose_branch"], layers.layer_norm(params["trunk_norm"], x))


def camera_head(params: Params, aggregated_last: jax.Array, config: CameraHeadConfig) -> list[jax.Array]:
    """Pose encodings of every refinement iteration.

    params: the `camera_head` subtree. aggregated_last: tokens of the last aggregator
    layer [B, S, P, 2E] (the camera token is index 0 of P). Returns `config.iters`
    activated encodings [B, S, 9] ("absT_quaR_FoV": t, quaternion xyzw, fov_h, fov_w);
    the last one is the model's prediction."""
    chex.assert_rank(aggregated_last, 4)
    b, s = aggregated_last.shape[:2]
    tokens = layers.layer_norm(params["token_norm"], aggregated_last[:, :, 0])

    empty = jnp.broadcast_to(params["empty_pose_tokens"], (b, s, params["empty_pose_tokens"].shape[-1]))

    def iteration(carry, _):
        pose_in, total = carry
        # The first iteration's encoding is its delta alone; later ones add to the running
        # sum. Upstream detaches the previous encoding, both as the sum and as the next
        # step's input (no gradient through earlier iterations); the first step's input,
        # the learned empty pose token, is not detached.
        raw = total + _refine(params, tokens, pose_in, config.num_heads)
        detached = jax.lax.stop_gradient(raw)
        return (detached, detached), activate_pose(raw, config.trans_act, config.quat_act, config.fl_act)

    # scanned: one compiled refinement step instead of `iters`
    _, stacked = jax.lax.scan(iteration, (empty, jnp.zeros_like(empty)), None, length=config.iters)
    outputs = list(stacked)
    chex.assert_shape(outputs, (b, s, 9))
    return outputs
