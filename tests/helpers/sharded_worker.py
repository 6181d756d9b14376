"""The sharded-forward and sharded-train-step checks, run by tests/parallel/test_sharded.py and
tests/parallel/test_sharded_train.py in a subprocess of their own:
XLA's host platform has to be told to make 4 CPU devices before JAX starts.

Prints one JSON object: per check, the measured errors and facts the test asserts on.
"""

import functools
import json
import os
import sys

os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"

from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository (run by path)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

import rvggt_jax  # noqa: E402
from rvggt_jax.ops.shards import FrameShards, split_frames  # noqa: E402
from rvggt_jax.model.heads.tracker import track_predictor  # noqa: E402
from rvggt_jax.parallel.sharded import frames_mesh, sharded_forward  # noqa: E402
from tests.helpers.paths import TINY  # noqa: E402

H, W = 42, 56  # 3 x 4 patches: every compression step has something to do
TRACKED = ("track", "vis", "conf")


def rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return float("inf")
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


def ring_gradient() -> dict:
    """The ring attention's backward on 4 devices (autodiff through the per-share
    `attention_with_lse` calls, its custom VJP, the log-sum-exp fold and the permutes:
    the cotangents go around the ring): gradients to the queries, every device's key
    share, its bias and a replicated `extra` key set, against autodiff of a plain float32
    reference attention over all keys. Relative errors per operand."""
    from rvggt_jax.ops.attention import log_sizes
    from rvggt_jax.ops.ring import ring_attention
    from tests.helpers.attention_reference import differentiable_reference, rel as rel32

    devices, per = 4, 12  # 12 queries and keys per device; 5 replicated extra keys
    rng = np.random.default_rng(5)
    q, k, v = (jnp.asarray(rng.standard_normal((1, devices * per, 2, 8)), jnp.float32) for _ in range(3))
    ek, ev = (jnp.asarray(rng.standard_normal((1, 5, 2, 8)), jnp.float32) for _ in range(2))
    sizes = np.floor(1 + 4 * rng.random((1, devices * per)))
    bias = log_sizes(jnp.asarray(sizes), jnp.asarray(rng.random((1, devices * per)) > 0.2))  # some removed
    eb = jnp.asarray(rng.standard_normal((1, 5)), jnp.float32)
    w = jnp.asarray(rng.standard_normal(q.shape), jnp.float32)
    shards = FrameShards(devices, devices, "frames")
    row = P(None, "frames")

    def ring(q, k, v, b, ek, ev, eb):
        # 512-byte logits blocks: every share runs the blocked loop (padded 8-row blocks)
        fn = jax.shard_map(lambda q, k, v, b, ek, ev, eb: ring_attention(q, k, v, b, shards, ((ek, ev, eb),),
                                                                         block_bytes=512),
                           mesh=frames_mesh(devices), in_specs=(row, row, row, row, P(), P(), P()), out_specs=row,
                           check_vma=False)
        return jnp.sum(fn(q, k, v, b, ek, ev, eb) * w)

    def reference(q, k, v, b, ek, ev, eb):
        cat = lambda a, e: jnp.concatenate([a, e], axis=1)  # noqa: E731
        return jnp.sum(differentiable_reference(q, cat(k, ek), cat(v, ev), cat(b, eb))[0] * w)

    args = (q, k, v, bias, ek, ev, eb)
    got = jax.jit(jax.grad(ring, range(7)))(*args)
    want = jax.jit(jax.grad(reference, range(7)))(*args)
    errors = {name: rel32(g, r) for name, g, r in zip(("q", "k", "v", "bias", "extra_k", "extra_v", "extra_bias"),
                                                       got, want)}
    # the backward's own permutes: the transposed shifts send the key shares' cotangents
    # back around the ring (the forward's loop has one permute per share array)
    permutes = {what: jax.jit(fn).lower(*args).as_text().count("collective_permute")
                for what, fn in (("forward", ring), ("gradient", jax.grad(ring, range(7))))}
    return {"errors": errors, "permutes": permutes}


def split_tracker(p, config, shards, fmaps, queries):
    """The tracker alone, traced with its frames split as `shards` (a shard_map's body)."""
    with split_frames(shards):
        return track_predictor(p, queries, fmaps, config)


def train_steps() -> dict:
    """One train step (forward, loss, gradient, clipping, AdamW) over 4 devices of
    `rvggt_jax.train.sharded` against `make_train_step` on one device: the micro layout at
    its smallest (2 layers, width 32; camera and depth heads), 4 scenes of 2 frames of
    28 x 42 whose depth masks differ (the loss's means must be the whole batch's). One
    layout holds all three splits (each compiled step costs ~50 s here): the scenes over
    "data" (2), each scene's frames around a ring of 2 ("frames"), the parameters and
    AdamW's moments split 4 ways (FSDP). The relative error of every metric; of the gradient (AdamW's
    first moment is 0.1 g; max error over the largest gradient); of the parameters after
    the step (per leaf, over its largest value) and of the update (in units of the
    learning rate), both where the gradient is above AdamW's noise floor
    (tests/train/test_accumulate.py: where |g| is ~1e-9 AdamW's first step amplifies
    rounding to a fraction of lr); how many state leaves are split (FSDP); and the
    refused layouts' messages."""
    from rvggt_jax import train
    from rvggt_jax.config import CameraHeadConfig, DPTHeadConfig
    from rvggt_jax.errors import InputError
    from rvggt_jax.train.sharded import (make_sharded_train_step, place_batch, place_state, train_layout,
                                          train_mesh)
    from tests.helpers.micro import micro_config

    config = micro_config(depth=2, enable_point=False, enable_track=False,
                          camera_head=CameraHeadConfig(num_heads=2, trunk_depth=1, iters=1),
                          dpt_head=DPTHeadConfig(features=8, out_channels=(4, 8, 16, 16),
                                                 intermediate_layer_idx=(0, 1, 1, 1)))
    scenes, frames, noise = 4, 2, 1e-6
    examples = []
    for i in range(scenes):
        ex = dict(train.synthetic_example(frames, (28, 42), seed=i))
        mask = np.array(ex["point_mask"])
        mask[:, : 3 * (i % 3 + 1)] = False  # different counts of valid pixels per scene
        ex["point_mask"], ex["depth"] = mask, np.where(mask, ex["depth"], 0.0)
        examples.append(ex)
    batch = train.stack(examples)
    tc = train.TrainConfig(learning_rate=1e-3, warmup_steps=0, total_steps=10)
    params = rvggt_jax.init_params(config, 0)
    state0 = train.init_state(params, tc)
    ref, ref_metrics = train.make_train_step(config, tc, donate=False)(state0, jax.device_put(batch))

    def mu(state):  # AdamW's first moment after one step: 0.1 x the (clipped) gradient
        return jax.tree.leaves(state.opt_state.inner_states["train"].inner_state[1][0].mu)

    g_ref = [np.asarray(g, np.float64) / 0.1 for g in mu(ref)]
    scale = max(np.abs(g).max() for g in g_ref)
    out: dict = {}
    for name, fpd, fsdp in (("data_frames_fsdp", 1, True),):
        layout = train_layout(4, scenes, frames, fpd, fsdp=fsdp)
        mesh = train_mesh(layout)
        step = make_sharded_train_step(config, tc, mesh, fsdp=fsdp, donate=False)
        got, metrics = step(place_state(state0, mesh, fsdp), place_batch(batch, mesh))
        grad = max(float(np.abs(np.asarray(g, np.float64) / 0.1 - r).max()) for g, r in zip(mu(got), g_ref)) / scale
        update, params_rel = 0.0, 0.0
        for p0, a, b, r in zip(jax.tree.leaves(params), jax.tree.leaves(got.params), jax.tree.leaves(ref.params),
                               g_ref):
            a, b, p0 = (np.asarray(x, np.float64) for x in (a, b, p0))
            signal = np.abs(r) > noise
            params_rel = max(params_rel, float(np.abs(a - b)[signal].max(initial=0.0) / max(np.abs(b).max(), 1e-12)))
            err = np.abs((a - p0) - (b - p0)) - np.spacing(np.abs(b).astype(np.float32)).astype(np.float64)
            update = max(update, float(err[signal].max(initial=0.0)) / tc.learning_rate)
        leaves = jax.tree.leaves(got)
        out[name] = {"mesh": dict(mesh.shape), "step": int(got.step),
                     "metrics": {k: rel(metrics[k], ref_metrics[k]) for k in ref_metrics},
                     "grad": grad, "update": update, "params": params_rel,
                     "split_leaves": sum(not a.sharding.is_fully_replicated for a in leaves),
                     "leaves": len(leaves)}
    # refused layouts: the message says what would work
    refused = {}
    for name, args in (("batch", (4, 2, 4, None)), ("frames", (4, 4, 4, 3)), ("too_many", (8, 8, 4, None))):
        try:
            train_layout(*args)
            refused[name] = "accepted"
        except InputError as e:
            refused[name] = str(e)
    out["refused"] = refused
    return out


def main() -> None:
    import time

    t0 = time.perf_counter()

    def tick(what):  # progress on stderr, for a slow run
        print(f"{time.perf_counter() - t0:7.1f}s {what}", file=sys.stderr, flush=True)

    params, config = rvggt_jax.load_pretrained(TINY)
    single = jax.jit(rvggt_jax.rvggt_forward, static_argnames="config")
    sharded = jax.jit(sharded_forward, static_argnames=("config", "mesh", "keep_padding"))
    queries = jnp.asarray([[[10.0, 12.0], [30.0, 40.0], [50.0, 20.0]]])
    report: dict = {"devices": len(jax.devices()), "runs": []}

    # (devices, preset, with track): 8 frames on 4 devices, and on 3 (uneven: padded to 9,
    # returned padded; the S-frame form is its slice). "+dup": duplicate_protected (the
    # protected tokens' own queries, replicated on every device, and their own rows)
    frames = 8
    cases = [(4, "dense", True), (4, "regime", True), (4, "fastvggt", False),
             (3, "dense", False), (3, "regime", True), (3, "regime+dup", False), (4, "avggt", False)]
    refs = {}
    for devices, preset, track in cases:
        uneven = frames % devices != 0
        name, _, dup = preset.partition("+")
        cfg = config if name == "dense" else config.with_compression(name, duplicate_protected=bool(dup))
        images = jax.random.uniform(jax.random.PRNGKey(frames), (1, frames, 3, H, W))
        qp = queries if track else None
        mesh = frames_mesh(devices)
        # the single-device forward, once per preset: with the tracker when any case of
        # the preset tracks (its other outputs are those of a forward without it)
        tracked = any(t for _, p, t in cases if p == preset)
        if preset not in refs:
            refs[preset] = single(params, images, cfg, queries if tracked else None)
        ref = refs[preset]
        out = sharded(params, images, cfg, mesh, qp, keep_padding=uneven)
        run = {"devices": devices, "frames": frames, "preset": preset, "track": track,
               "sharded": out["depth"].sharding.spec == P(None, "frames")}
        if uneven:
            real = np.asarray(out.pop("frame_mask"))
            run["padded_frames"] = int(out["depth"].shape[1])
            run["padded_mask"] = real.tolist()
            out = {k: (v[:, real] if k != "pose_enc_list" else [a[:, real] for a in v]) for k, v in out.items()}
        run["errors"] = {k: rel(out[k], ref[k]) for k in ref if k not in ("pose_enc_list",) + TRACKED}
        run["pose_enc_list"] = max(rel(a, b) for a, b in zip(out["pose_enc_list"], ref["pose_enc_list"]))
        if track:
            run["track_errors"] = {k: rel(out[k], ref[k]) for k in TRACKED}
            run["track_finite"] = bool(all(np.isfinite(np.asarray(out[k])).all() for k in TRACKED))
            run["track_frame0"] = float(np.abs(np.asarray(out["track"])[:, 0] - np.asarray(queries)).max())
        report["runs"].append(run)
        tick(f"{devices} devices {preset}")
    # the long-sequence routes on each device (as at 1000 frames): a token chunk of 2 KiB
    # runs every loop in chunks, each taking its rows of the device's RoPE tables from one
    # frame's (chunks.Periodic); against the single-device forward of the default chunks
    from rvggt_jax.ops import chunks
    from rvggt_jax.model import layers

    long_cfg = config.with_compression("regime")
    long_images = jax.random.uniform(jax.random.PRNGKey(frames), (1, frames, 3, H, W))
    ref = refs["regime"]
    saved = chunks.TOKEN_CHUNK_BYTES
    chunks.TOKEN_CHUNK_BYTES = 2048
    try:
        per_frame = long_cfg.patch_start_idx + (H // 14) * (W // 14)
        frame = layers.RopeTables.from_positions(jnp.zeros((1, per_frame, 2), jnp.int32), long_cfg.head_dim,
                                                 long_cfg.rope_freq)
        periodic = isinstance(layers.RopeTables.of_sequence(frame, frames // 4).cos, chunks.Periodic)
        long = jax.jit(lambda p, x: sharded_forward(p, x, long_cfg, frames_mesh(4)))(params, long_images)
    finally:
        chunks.TOKEN_CHUNK_BYTES = saved
    report["long_routes"] = {"periodic": periodic,
                             "errors": {k: rel(long[k], ref[k]) for k in ("depth", "world_points", "pose_enc")}}
    tick("long-sequence routes")

    # one compilation per input shape: new values, same shapes
    before = sharded._cache_size()
    sharded(params, images * 0.5, cfg, mesh, qp, keep_padding=uneven)  # (in [0, 1]: no range warning)
    report["recompiled"] = sharded._cache_size() - before

    # the tracker alone on the same feature maps: what frames split changes, and nothing else
    p = params["track_head"]["tracker"]
    c = p["fmap_norm"]["scale"].shape[0]
    tracker = {}
    fmaps = jax.random.normal(jax.random.PRNGKey(1), (1, frames, 14, 17, c))
    ref = jax.jit(lambda f, q: track_predictor(p, q, f, config.track_head))(fmaps, queries)
    for devices in (4, 3):
        shards = FrameShards(frames, devices, "frames")
        fm = jnp.pad(fmaps, ((0, 0), (0, shards.padded - frames), (0, 0), (0, 0), (0, 0)))
        fn = jax.shard_map(functools.partial(split_tracker, p, config.track_head, shards),
                           mesh=frames_mesh(devices), in_specs=(P(None, "frames"), P()),
                           out_specs=(P(None, None, "frames"), P(None, "frames"), P(None, "frames")),
                           check_vma=False)
        out = jax.jit(fn)(fm, queries)
        tracker[f"{devices} devices"] = {"coords": rel(np.asarray(out[0])[:, :, :frames], ref[0]),
                                          "vis": rel(np.asarray(out[1])[:, :frames], ref[1]),
                                          "conf": rel(np.asarray(out[2])[:, :frames], ref[2])}
    report["tracker"] = tracker
    tick("tracker")

    # XLA's plan of the sharded program on abstract inputs (nothing runs): per device, the
    # working memory of tests/planning/test_memory.py's long sequence (200 frames, width
    # 256) split 4 ways against one device's
    from rvggt_jax.planning.memory import memory_report
    from tests.helpers.long_sequence import BASE, H as MH, S as MS, W as MW

    cfg = BASE.with_compression("regime")
    one = memory_report(cfg, MS, MH, MW)
    four = memory_report(cfg, MS, MH, MW, mesh=frames_mesh(4))
    tick("plans")
    report["plan"] = {"one": one.temp_bytes + one.output_bytes, "four": four.temp_bytes + four.output_bytes}

    # meshes as a user makes them (jax.make_mesh, explicit axes by default in recent JAX,
    # or auto): batch 2, 5 frames over 3 devices (padded to 6, sliced back to 5)
    user_images = jax.random.uniform(jax.random.PRNGKey(5), (2, 5, 3, 28, 28))
    user_ref = single(params, user_images, config)
    report["user_meshes"] = {}
    for axis_type in (jax.sharding.AxisType.Explicit, jax.sharding.AxisType.Auto):
        mesh = jax.make_mesh((3,), ("frames",), devices=jax.devices()[:3], axis_types=(axis_type,))
        out = sharded(params, user_images, config, mesh)
        report["user_meshes"][axis_type.name] = {
            "shape": list(out["depth"].shape),
            "errors": {k: rel(out[k], user_ref[k]) for k in ("depth", "world_points", "pose_enc", "depth_conf")}}
    report["default_axis_type"] = jax.make_mesh((1,), ("frames",)).axis_types[0].name
    tick("user meshes")

    # a mesh without a "frames" axis is refused
    try:
        sharded_forward(params, jnp.zeros((1, 4, 3, H, W)), config, jax.make_mesh((4,), ("data",)))
        report["no_frames_axis"] = "accepted"
    except ValueError as e:
        report["no_frames_axis"] = str(e)
    report["ring_gradient"] = ring_gradient()
    tick("ring gradient")
    report["train_steps"] = train_steps()
    tick("train steps")
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    if sys.argv[1:] == ["ring_gradient"]:  # that check alone (development)
        json.dump(ring_gradient(), sys.stdout)
    elif sys.argv[1:] == ["train_steps"]:
        json.dump(train_steps(), sys.stdout)
    else:
        main()
