"""Fine-tuning: the loss decreases on synthetic scenes, a run resumed from an Orbax
checkpoint continues exactly, frozen parameters stay bit-equal, remat changes XLA's
memory plan and not the values; the losses and the data reader on their own;
`train.finetune` on a data folder (frame buckets, exact resume)."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import rvggt_jax
from rvggt_jax import train
from rvggt_jax.config import REMAT_POLICIES, DinoConfig
from rvggt_jax.model.forward import rvggt_forward
from rvggt_jax.synthetic import make_scene, write_scene
from tests.helpers.micro import micro_config, plan_config, train_config

SIZE = (28, 42)
FRAMES = 3
STEPS = 30
SAVE_AT = 5


def _batches(n: int) -> list[dict]:
    """Four synthetic scenes, cycled: batch i is scene i % 4."""
    examples = [train.synthetic_example(FRAMES, SIZE, seed=i) for i in range(4)]
    return [jax.device_put(train.stack([examples[i % 4]])) for i in range(n)]


@pytest.fixture(scope="module")
def setup():
    # camera + depth heads (the point head is the depth head's twin; the track head needs
    # tracks), 3 aggregator layers (with 2, "full" remat's recomputation takes more
    # temporary memory than it saves): one compiled train step shared by the tests below
    config = train_config(layers=3)
    tc = train.TrainConfig(learning_rate=1e-3, warmup_steps=5, total_steps=STEPS)
    params = rvggt_jax.init_params(config, 0)
    batches = _batches(STEPS + 1)
    state0 = train.init_state(params, tc)
    step = train.make_train_step(config, tc, donate=False)
    compiled = step.lower(state0, batches[0]).compile()
    return config, tc, params, batches, state0, compiled


@pytest.fixture(scope="module")
def trajectory(setup, tmp_path_factory):
    """30 uninterrupted steps (loss of each), the state saved after SAVE_AT steps."""
    config, tc, _, batches, state, compiled = setup
    ckpt = tmp_path_factory.mktemp("ckpt")
    losses, states = [], []
    for i in range(STEPS + 1):
        if i == SAVE_AT:
            train.save_state(state, ckpt, model_config=config, train_config=tc)
        state, metrics = compiled(state, batches[i])
        losses.append(float(metrics["loss_objective"]))
        states.append(state)
    return losses, states, ckpt


def test_loss_decreases_over_30_steps(trajectory):
    losses, _, _ = trajectory
    assert all(np.isfinite(losses))
    # the same batch (scene 0) before training and after 28 steps: no batch-to-batch noise
    assert losses[28] < 0.6 * losses[0], losses
    # and the trend over all scenes: the last five steps well below the first five
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5]), losses


def test_resume_from_checkpoint_continues_exactly(setup, trajectory):
    config, tc, params, batches, state0, compiled = setup
    losses, states, ckpt = trajectory
    meta = json.loads((ckpt / train.step.META_NAME).read_text())
    assert rvggt_jax.VGGTConfig.from_dict(meta["model"]) == config
    assert train.TrainConfig.from_dict(meta["train"]) == tc
    assert train.latest_step(ckpt) == SAVE_AT
    state = train.restore_state(ckpt, state0)
    assert int(state.step) == SAVE_AT
    for i in range(SAVE_AT, 11):
        state, metrics = compiled(state, batches[i])
        assert float(metrics["loss_objective"]) == losses[i]  # bit for bit
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(states[10])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_restore_without_checkpoint_is_an_error(setup, tmp_path):
    with pytest.raises(FileNotFoundError, match="no train-state checkpoint"):
        train.restore_state(tmp_path, setup[4])


def test_frozen_aggregator_stays_bit_equal(setup):
    """train="heads" on `setup`'s batches, in the layout with the depth head alone
    (`plan_config("depth")`: the cheapest heads-only step to compile)."""
    batches = setup[3]
    config = plan_config("depth")
    params = rvggt_jax.init_params(config, 0)
    tc = train.TrainConfig(learning_rate=1e-3, warmup_steps=0, total_steps=10, train="heads")
    labels = train.param_labels(params, tc.train)
    assert set(jax.tree.leaves(labels["aggregator"])) == {"frozen"}
    assert set(jax.tree.leaves(labels["depth_head"])) == {"train"}
    step = train.make_train_step(config, tc, donate=False)
    state = train.init_state(params, tc)
    for i in range(2):
        state, metrics = step(state, batches[i])
    for a, b in zip(jax.tree.leaves(state.params["aggregator"]), jax.tree.leaves(params["aggregator"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    moved = [not np.array_equal(np.asarray(a), np.asarray(b))
             for a, b in zip(jax.tree.leaves(state.params["depth_head"]), jax.tree.leaves(params["depth_head"]))]
    assert any(moved)
    assert float(metrics["grad_norm"]) > 0
    with pytest.raises(ValueError, match="matches no parameter"):
        train.param_labels(params, ("depht_head",))


def _checkpoints(jaxpr) -> list:
    """The policy of every `jax.checkpoint` in `jaxpr` and the jaxprs inside it (scans, conds)."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("checkpoint", "remat2"):  # (JAX's name for it, jax 0.10: remat2)
            found.append(eqn.params.get("policy"))
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else (value,):
                inner = sub if hasattr(sub, "eqns") else getattr(sub, "jaxpr", None)
                if hasattr(inner, "eqns"):
                    found += _checkpoints(inner)
    return found


def _saves(policy) -> tuple[bool, bool]:
    """(keeps the ordering zeros, keeps a matmul's output) under a checkpoint `policy`."""
    from jax.ad_checkpoint import checkpoint_name

    from rvggt_jax.ops.ordering import ORDER_NAME

    def kept(fn, *args):
        eqns = jax.make_jaxpr(fn)(*args).jaxpr.eqns
        return any(policy(e.primitive, *[v.aval for v in e.invars], **e.params) for e in eqns)

    a = jnp.ones((4, 4))
    return kept(lambda x: checkpoint_name(x * 2, ORDER_NAME), a), kept(lambda x: x @ x, a)


def test_remat_policies_checkpoint_what_they_say():
    """Traced only: each policy's `jax.checkpoint`s in the forward of `setup`'s layout with
    a DINO of 2 blocks."""
    config = micro_config(enable_point=False, enable_track=False, dino=DinoConfig(depth=2, num_heads=2))
    assert config.with_remat(True).remat == "full" and config.with_remat(False).remat == "none"
    assert config.with_remat(True) == config.with_remat("full") == dataclasses.replace(config, remat="full")
    assert rvggt_jax.VGGTConfig.from_dict({**config.to_dict(), "remat": True}).remat == "full"  # an older train.json
    with pytest.raises(ValueError, match="remat must be one of"):
        config.with_remat("everything")
    from rvggt_jax.app.cli import build_parser

    parse = build_parser().parse_args
    assert [parse(["finetune", "d", "--out", "o", *flag]).remat for flag in ([], ["--remat"], ["--remat=layers"])] == [
        "none", "full", "layers"]
    # the parser (it imports no JAX) takes every policy of the config
    assert [parse(["finetune", "d", "--out", "o", f"--remat={p}"]).remat for p in REMAT_POLICIES] == list(
        REMAT_POLICIES)
    params = jax.eval_shape(lambda: rvggt_jax.init_params(config, 0))
    images = jax.ShapeDtypeStruct((1, FRAMES, 3) + SIZE, jnp.float32)
    found = {policy: _checkpoints(jax.make_jaxpr(rvggt_forward, static_argnums=2)(
        params, images, config.with_remat(policy)).jaxpr) for policy in REMAT_POLICIES}
    # the DINO block scan and the aggregator's two scans (layers 0-2 write their global
    # halves, the last layer is the residual stream); "full" adds the patch embed and the
    # heads' frame groups; "dots" saves the blocks' matmul outputs
    blocks = 3
    assert {p: len(f) for p, f in found.items()} == {"none": 0, "layers": blocks, "full": blocks + 2,
                                                     "dots": blocks + 2}
    # (every checkpoint keeps the ordering zeros, ops.ordering.ORDER_NAME)
    keeps = {p: [_saves(policy) for policy in f] for p, f in found.items()}
    assert keeps["full"] == [(True, False)] * (blocks + 2)
    assert sorted(keeps["dots"]) == [(True, False)] * 2 + [(True, True)] * blocks


def test_remat_changes_memory_plan_not_values(setup):
    # remat=True is "full": the aggregator layers, DINO as a whole and the heads' frame groups
    config, tc, params, batches, state0, compiled = setup
    step_r = train.make_train_step(config.with_remat(), tc, donate=False)
    compiled_r = step_r.lower(state0, batches[0]).compile()
    plain, remat = compiled.memory_analysis(), compiled_r.memory_analysis()
    assert remat.temp_size_in_bytes < plain.temp_size_in_bytes, (remat, plain)
    s1, m1 = compiled(state0, batches[0])
    s2, m2 = compiled_r(state0, batches[0])
    np.testing.assert_allclose(float(m2["loss_objective"]), float(m1["loss_objective"]), rtol=1e-6)

    # the gradients, through AdamW's first moment after one step (0.1 x the clipped
    # gradient; the parameters themselves cannot tell: the warm-up's first rate is 0)
    def grads(state):
        mu = state.opt_state.inner_states["train"].inner_state[1][0].mu
        return [np.asarray(g, np.float64) / 0.1 for g in jax.tree.leaves(mu)]

    g1, g2 = grads(s1), grads(s2)
    scale = max(np.abs(g).max() for g in g1)
    assert scale > 0
    worst = max(np.abs(a - b).max() for a, b in zip(g2, g1))
    assert worst <= 1e-5 * scale, (worst, scale)  # recomputation may round differently (7e-8 of 0.35 here)


# ---- losses, schedule and data on their own (no model) ----------------------------------


def test_regression_loss_of_a_constant_offset():
    """pred = gt + 0.1 (one channel), conf 2: the conf term is 0.1*2 - 0.2 log 2; the
    finite differences of a constant residual vanish, leaving -0.2 log 2 per scale and
    axis (3 scales x 2 axes)."""
    cfg = train.LossConfig()
    gt = jnp.asarray(np.random.default_rng(0).random((1, 2, 8, 8, 3)), jnp.float32)
    pred = gt.at[..., 1].add(0.1)
    mask = jnp.ones((1, 2, 8, 8), bool).at[0, 1, :4].set(False)
    loss = jax.jit(train.regression_loss, static_argnums=4)  # (one program for both calls)
    out = loss(pred, jnp.full((1, 2, 8, 8), 2.0), gt, mask, cfg)
    np.testing.assert_allclose(float(out["conf"]), 0.2 - 0.2 * np.log(2), rtol=1e-5)
    np.testing.assert_allclose(float(out["reg"]), 0.1, rtol=1e-5)
    np.testing.assert_allclose(float(out["grad"]), 6 * (-0.2 * np.log(2)), rtol=1e-4)
    empty = loss(pred, jnp.full((1, 2, 8, 8), 2.0), gt, jnp.zeros_like(mask), cfg)
    assert float(empty["conf"]) == 0.0 and float(empty["grad"]) == 0.0  # no valid pixel: 0, not NaN


def test_camera_loss_is_zero_at_the_truth_and_weighted_by_iteration():
    ex = train.synthetic_example(3, SIZE, seed=1)
    ext, k = jnp.asarray(ex["extrinsics"])[None], jnp.asarray(ex["intrinsics"])[None]
    from rvggt_jax.geometry import extri_intri_to_pose_encoding

    gt = jax.jit(extri_intri_to_pose_encoding, static_argnums=2)(ext, k, SIZE)
    cfg = train.LossConfig()
    loss = jax.jit(train.camera_loss, static_argnums=(3, 4))  # (one program for both calls)
    assert float(loss([gt, gt], ext, k, SIZE, cfg)["loss_camera"]) == 0.0
    off = gt.at[..., 0].add(0.3)  # translation x off by 0.3 in every frame: mean over 3 T entries = 0.1
    got = loss([off, gt], ext, k, SIZE, cfg)["loss_camera"]
    np.testing.assert_allclose(float(got), cfg.camera_gamma * cfg.weight_trans * 0.1, rtol=1e-5)


def test_schedule_warms_up_then_decays():
    tc = train.TrainConfig(learning_rate=1e-3, warmup_steps=10, total_steps=100, final_lr_ratio=0.1)
    lr = jax.jit(train.schedule(tc))  # (one program for every step below)
    assert float(lr(0)) == 0.0
    np.testing.assert_allclose(float(lr(10)), 1e-3, rtol=1e-6)
    np.testing.assert_allclose(float(lr(100)), 1e-4, rtol=1e-5)
    assert float(lr(5)) < float(lr(10)) and float(lr(50)) < float(lr(10))
    with pytest.raises(ValueError, match="train must be"):
        train.TrainConfig(train="everything").validate()


def test_example_is_normalised_like_upstream():
    ex = train.synthetic_example(4, SIZE, seed=2)
    np.testing.assert_allclose(ex["extrinsics"][0], np.eye(3, 4), atol=1e-6)
    pts = ex["world_points"][ex["point_mask"]]
    np.testing.assert_allclose(np.linalg.norm(pts, axis=-1).mean(), 1.0, rtol=1e-5)  # unit mean distance
    # frame 0's points are its depth along its rays (camera 0 = world)
    assert np.allclose(ex["world_points"][0][..., 2][ex["point_mask"][0]], ex["depth"][0][ex["point_mask"][0]],
                       rtol=1e-5)


def test_folder_reader_gives_the_synthetic_example(tmp_path):
    """A scene written in the folder layout reads back as the same example (PNG images,
    .npy depth), and 16-bit PNG depth reads within its quantisation."""
    scene = make_scene(frames=FRAMES, height=SIZE[0], width=SIZE[1], seed=3)
    write_scene(scene, "folder", tmp_path)
    (sc,) = train.folder_scenes(tmp_path)
    got = train.scene_example(sc, FRAMES, SIZE)
    want = train.make_example(scene.images, scene.extrinsics, scene.intrinsics, scene.depth)
    assert got.keys() == want.keys()
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=1e-6, atol=1e-6, err_msg=k)

    from PIL import Image

    d = tmp_path / scene.name / "depth"
    scale = 0.001
    for f in sorted(d.glob("*.npy")):
        Image.fromarray(np.round(np.load(f) / scale).astype(np.uint16)).save(f.with_suffix(".png"))
        f.unlink()
    (d / "depth_scale.json").write_text(json.dumps({"scale": scale}))
    (sc,) = train.folder_scenes(tmp_path)
    got16 = train.scene_example(sc, FRAMES, SIZE, rng=None)
    assert np.abs(got16["depth"] - want["depth"]).max() < scale  # (normalised by a scale ~3)
    with pytest.raises(rvggt_jax.InputError, match="frames"):
        train.scene_example(sc, FRAMES + 5, SIZE)
    with pytest.raises(rvggt_jax.InputError, match="multiples of 14"):
        train.synthetic_example(2, (30, 42))


def test_finetune_cli_errors_are_one_line(tmp_path, capsys):
    from rvggt_jax.app.cli import main

    assert main(["finetune", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 1
    assert "no such data folder" in capsys.readouterr().err
    assert main(["finetune", str(tmp_path), "--out", str(tmp_path / "o"), "--size", "224by294"]) == 1
    assert "--size must be HxW" in capsys.readouterr().err
    assert main(["finetune", str(tmp_path), "--out", str(tmp_path / "o")]) == 1  # neither weights nor config
    assert "--weights" in capsys.readouterr().err


# ---- train.finetune on a data folder: frame buckets, exact resume -----------------------

# steps 0-3 of seed 1 draw 2, 3, 3, 2 frames (asserted below): both buckets before and after the stop
FT_OPTS = train.FinetuneOptions(steps=STEPS, frames=(2, FRAMES), buckets=(2, FRAMES), size=SIZE, learning_rate=1e-3,
                                warmup_steps=5, save_every=100, log_every=1, seed=1, prefetch=1, stop_at=4)


@pytest.fixture(scope="module")
def finetuned(tmp_path_factory):
    """`train.finetune` of the smallest layout (2 layers, the camera head only: its two
    programs compile fastest) on two 4-frame scenes: 4 steps at once, and 2 steps, stop,
    2 more (resumed)."""
    config = plan_config("camera")
    params = rvggt_jax.init_params(config, 0)
    root = tmp_path_factory.mktemp("finetune")
    for i in range(2):
        write_scene(make_scene(frames=4, height=SIZE[0], width=SIZE[1], seed=i), "folder", root / "data")
    logs = {"full": [], "part": []}
    own = lambda: jax.tree.map(jnp.copy, params)  # noqa: E731 (finetune's first step donates its params)
    train.finetune(root / "data", root / "full", own(), config, FT_OPTS, log=logs["full"].append, progress=False)
    for stop in (2, 4):
        train.finetune(root / "data", root / "part", own(), config, dataclasses.replace(FT_OPTS, stop_at=stop),
                       log=logs["part"].append, progress=False)
    return root, logs, config, params


def test_finetune_compiles_one_program_per_frame_bucket(finetuned):
    root, logs, config, _ = finetuned
    recs = [json.loads(x) for x in (root / "full" / "log.jsonl").read_text().splitlines()]
    assert [r["frames"] for r in recs] == [2, 3, 3, 2]
    (step,) = [f for (c, _), f in train.loop._STEPS.items() if c == config]
    assert step._cache_size() == len(FT_OPTS.buckets) == 2  # none more on resuming
    compiled = [m.split(" in ")[0] for m in logs["full"] + logs["part"] if m.startswith("compiled the train step")]
    assert compiled == ["compiled the train step for 2 frames of 28x42", "compiled the train step for 3 frames of 28x42"]
    assert any(m.startswith("stopped after step 4 of 30") for m in logs["full"])
    with Image.open(root / "full" / "loss.png") as im:
        assert im.size == (640, 360)


def test_finetune_resumed_equals_uninterrupted(finetuned):
    root, logs, _, params = finetuned
    assert any(m.startswith("resuming from step 2") for m in logs["part"])
    # every logged metric bit for bit (json keeps float64 exactly), each step once
    assert (root / "part" / "log.jsonl").read_text() == (root / "full" / "log.jsonl").read_text()
    tc = train.TrainConfig.from_dict(json.loads((root / "part" / "train.json").read_text())["train"])
    like = train.init_state(params, tc)
    a, b = train.restore_state(root / "full", like), train.restore_state(root / "part", like)
    assert int(a.step) == int(b.step) == 4
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_rerunning_a_finished_or_stopped_run_trains_nothing(finetuned, tmp_path):
    """The same command again used to end in Orbax's StepAlreadyExistsError."""
    import shutil

    root, _, config, params = finetuned
    ck = shutil.copytree(root / "full", tmp_path / "run")  # at step 4 (--stop-at 4)
    before = (ck / "log.jsonl").read_text()
    log = []
    run = lambda **kw: train.finetune(root / "data", ck, params, config,  # noqa: E731
                                      dataclasses.replace(FT_OPTS, **kw), log=log.append, progress=False)
    assert run() == ck / "state" / "4"
    assert any(m.startswith("already at step 4 of 30") for m in log)
    # a larger --steps says that the schedule is re-planned (here still stopped at 4)
    assert run(steps=40) == ck / "state" / "4"
    assert any("re-planned for 40 steps" in m and "began with 30" in m for m in log)
    # finished at --steps 4: the weights written once, then only said
    assert run(steps=4, stop_at=None) == ck / "model" and (ck / "model" / "config.json").is_file()
    assert run(steps=4, stop_at=None) == ck / "model"
    assert sum(m.startswith(f"finished: {ck} holds step 4") for m in log) == 2
    assert (ck / "log.jsonl").read_text() == before and train.latest_step(ck) == 4
