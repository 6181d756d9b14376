"""The sharded-forward checks, run by tests/test_sharded.py in a subprocess of its own:
XLA's host platform has to be told to make 4 CPU devices before JAX starts.

Prints one JSON object: per check, the measured errors and facts the test asserts on.
"""

import json
import os
import sys

os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"

from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

import rvggt_jax  # noqa: E402
from rvggt_jax.frames import FrameShards  # noqa: E402
from rvggt_jax.heads.tracker import track_predictor  # noqa: E402
from rvggt_jax.sharded import frames_mesh, sharded_forward  # noqa: E402

TINY = Path(__file__).parent / "data" / "vggt_tiny"
H, W = 42, 56  # 3 x 4 patches: every compression step has something to do
TRACKED = ("track", "vis", "conf")


def rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return float("inf")
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


def main() -> None:
    params, config = rvggt_jax.load_pretrained(TINY)
    single = jax.jit(rvggt_jax.rvggt_forward, static_argnames="config")
    sharded = jax.jit(sharded_forward, static_argnames=("config", "mesh", "keep_padding"))
    queries = jnp.asarray([[[10.0, 12.0], [30.0, 40.0], [50.0, 20.0]]])
    report: dict = {"devices": len(jax.devices()), "runs": []}

    # (devices, frames, preset, with track): 8 frames on 4 devices; 7 (uneven) on 3, in the
    # padded form (the S-frame form is its slice)
    cases = [(4, 8, "dense", True), (4, 8, "regime", True), (4, 8, "fastvggt", False),
             (3, 7, "dense", True), (3, 7, "regime", False), (3, 7, "fastvggt", False)]
    for devices, frames, preset, track in cases:
        uneven = frames % devices != 0
        cfg = config if preset == "dense" else config.with_compression(preset)
        images = jax.random.uniform(jax.random.PRNGKey(frames), (1, frames, 3, H, W))
        qp = queries if track else None
        mesh = frames_mesh(devices)
        ref = single(params, images, cfg, qp)
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
        # one compilation per input shape: new values, same shapes
        before = sharded._cache_size()
        sharded(params, images + 0.25, cfg, mesh, qp, keep_padding=uneven)
        run["recompiled"] = sharded._cache_size() - before
        report["runs"].append(run)

    # the tracker alone on the same feature maps: what frames split changes, and nothing else
    p = params["track_head"]["tracker"]
    c = p["fmap_norm"]["scale"].shape[0]
    tracker = {}
    for devices, frames in ((4, 8), (3, 7)):
        fmaps = jax.random.normal(jax.random.PRNGKey(1), (1, frames, 14, 17, c))
        ref = track_predictor(p, queries, fmaps, config.track_head)
        shards = FrameShards(frames, devices, "frames")
        fm = jnp.pad(fmaps, ((0, 0), (0, shards.padded - frames), (0, 0), (0, 0), (0, 0)))
        fn = jax.shard_map(lambda f, q: track_predictor(p, q, f, config.track_head, shards=shards),
                           mesh=frames_mesh(devices), in_specs=(P(None, "frames"), P()),
                           out_specs=(P(None, None, "frames"), P(None, "frames"), P(None, "frames")),
                           check_vma=False)
        out = fn(fm, queries)
        tracker[f"{devices}x{frames}"] = {"coords": rel(np.asarray(out[0])[:, :, :frames], ref[0]),
                                          "vis": rel(np.asarray(out[1])[:, :frames], ref[1]),
                                          "conf": rel(np.asarray(out[2])[:, :frames], ref[2])}
    report["tracker"] = tracker

    # a mesh without a "frames" axis is refused
    try:
        sharded_forward(params, jnp.zeros((1, 4, 3, H, W)), config, jax.make_mesh((4,), ("data",)))
        report["no_frames_axis"] = "accepted"
    except ValueError as e:
        report["no_frames_axis"] = str(e)
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    main()
