"""Gradient accumulation (issue 25, item 3): a batch in micro-batches gives the update of
the whole batch at once (1e-6, float32, the micro layout), also when the scenes' masks
differ; the losses' shared denominators on their own; bad --accumulate values named."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rvggt_jax
from rvggt_jax import train
from rvggt_jax.train import losses
from tests.helpers.micro import train_config

SIZE = (28, 42)
FRAMES = 2


def _batch(scenes: int = 2) -> dict:
    """Synthetic scenes, each with a different part of its depth unknown (the masked
    means then have different counts per scene: averaging per-scene losses would not
    give the batch's loss)."""
    examples = []
    for i in range(scenes):
        ex = dict(train.synthetic_example(FRAMES, SIZE, seed=i))
        mask = np.array(ex["point_mask"])
        mask[:, : 3 * (i + 1)] = False  # the top 3, 6, ... rows unknown
        ex["point_mask"] = mask
        ex["depth"] = np.where(mask, ex["depth"], 0.0)
        examples.append(ex)
    return jax.device_put(train.stack(examples))


# AdamW's first step is lr * g / (|g| + 1e-8): a gradient difference dg moves it by
# lr * 1e-8 dg / (|g| + 1e-8)^2, so float32 rounding (dg ~ 1e-11 here, ~1e-7 of the
# gradient's scale, from the batch-size-dependent ops) is amplified to ~1e-2 lr where |g|
# is ~1e-9 (the attention's K biases, to which softmax is invariant, are all noise),
# in two correct runs alike. The update is compared where |g| >= NOISE (there the
# amplification is < 1e-6 lr), the gradient everywhere.
NOISE = 1e-6


def test_accumulated_step_equals_the_whole_batch():
    # the micro layout at its smallest: 2 aggregator layers, a camera trunk of one block and
    # one iteration, the depth head (its masked means)
    config = train_config()
    params = rvggt_jax.init_params(config, 0)
    batch = _batch(2)
    tc = train.TrainConfig(learning_rate=1e-3, warmup_steps=0, total_steps=10)
    state0 = train.init_state(params, tc)
    whole, m_whole = train.make_train_step(config, tc, donate=False)(state0, batch)
    acc, m_acc = train.make_train_step(config, dataclasses.replace(tc, accumulate=2), donate=False)(state0, batch)
    for k in m_whole:  # every loss part is the whole batch's, and the gradient's norm
        np.testing.assert_allclose(float(m_acc[k]), float(m_whole[k]), rtol=1e-6, err_msg=k)
    # the gradients (AdamW's first moment is 0.1 g) and the update, per element
    mu_a, mu_w = (s.opt_state.inner_states["train"].inner_state[1][0].mu for s in (acc, whole))
    scale = max(float(np.abs(np.asarray(g)).max()) for g in jax.tree.leaves(mu_w)) / 0.1
    worst, compared, total = 0.0, 0, 0
    for (path, ga), gw, p0, a, b in zip(jax.tree_util.tree_leaves_with_path(mu_a), jax.tree.leaves(mu_w),
                                        jax.tree.leaves(params), jax.tree.leaves(acc.params),
                                        jax.tree.leaves(whole.params)):
        ga, gw = np.asarray(ga, np.float64) / 0.1, np.asarray(gw, np.float64) / 0.1
        p0 = np.asarray(p0, np.float64)  # (numpy: no program compiled per parameter shape)
        # (float32 rounding of the batch-size-dependent ops: ~1e-7 of the gradient's scale)
        assert np.abs(ga - gw).max() <= 1e-6 * scale, jax.tree_util.keystr(path)
        signal = np.abs(gw) > NOISE
        update_err = np.abs((np.asarray(a, np.float64) - p0) - (np.asarray(b, np.float64) - p0))
        # 1e-6 of the step (~lr), beyond the float32 rounding of the updated parameter itself
        # (its spacing: 1.5e-8 at 0.25, i.e. 1.5e-5 lr)
        excess = update_err - np.spacing(np.abs(np.asarray(b, np.float32))).astype(np.float64)
        worst = max(worst, float(excess[signal].max(initial=0.0)) / tc.learning_rate)
        compared += int(signal.sum())
        total += signal.size
    assert worst <= 1e-6, worst
    # (60% of this micro model's parameters have |g| > NOISE: the update of most of them)
    assert compared >= 0.5 * total, (compared, total)


def _outputs(batch: dict, seed: int) -> dict:
    """Random model outputs of the shapes the losses read (no model)."""
    rng = np.random.default_rng(seed)
    b, s, _, h, w = batch["images"].shape
    return {"pose_enc_list": [jnp.asarray(rng.standard_normal((b, s, 9)), jnp.float32) for _ in range(2)],
            "depth": jnp.asarray(rng.random((b, s, h, w, 1)), jnp.float32),
            "depth_conf": jnp.asarray(1 + rng.random((b, s, h, w)), jnp.float32)}


def test_shared_denominators_make_micro_batch_losses_add_up():
    batch = _batch(4)
    out = _outputs(batch, 0)

    @jax.jit
    def three(out, batch):
        whole = losses.vggt_loss(out, batch)[0]
        totals = losses.record_denominators(lambda: losses.vggt_loss(out, batch))
        shared, naive = 0.0, 0.0
        for k in range(2):
            mb = jax.tree.map(lambda x: x[2 * k: 2 * k + 2], (out, batch))
            with losses.shared_denominators(totals):
                shared += losses.vggt_loss(*mb)[0]
            naive += losses.vggt_loss(*mb)[0] / 2  # each micro-batch's own means, averaged
        return whole, shared, naive, totals

    whole, shared, naive, totals = three(out, batch)
    np.testing.assert_allclose(float(shared), float(whole), rtol=1e-6)
    assert abs(float(naive) - float(whole)) > 1e-4 * abs(float(whole))  # the masks matter
    with pytest.raises(RuntimeError, match="means"):  # a different loss under the batch's counts
        with losses.shared_denominators(totals[:3]):
            jax.eval_shape(losses.vggt_loss, out, batch)  # (traced: nothing compiled)


def test_bad_accumulate_is_named(tmp_path):
    batch = {"images": jnp.zeros((4, 2, 3, 28, 42))}
    with pytest.raises(ValueError, match=r"accumulate=3 does not divide the batch of 4 scenes: use accumulate in "
                                         r"\[1, 2, 4\]"):
        train.step.micro_batches(batch, 3)
    with pytest.raises(ValueError, match="integer >= 1"):
        train.TrainConfig(accumulate=0).validate()
    opts = train.FinetuneOptions(batch=4, accumulate=3)
    with pytest.raises(rvggt_jax.InputError, match=r"--accumulate 3 must divide --batch 4.*\[1, 2, 4\]"):
        train.finetune(tmp_path, tmp_path / "out", {}, None, opts)


def test_finetune_cli_takes_accumulate():
    from rvggt_jax.app.cli import build_parser

    args = build_parser().parse_args(["finetune", "data", "--out", "o", "--batch", "4", "--accumulate", "2"])
    assert (args.batch, args.accumulate) == (4, 2)
