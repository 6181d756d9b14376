"""RegimeVGGT presets against dense: compile time, steady wall time, speedup vs the cost model.

Random weights; the aggregator trunk of VGGT (24 frame blocks + 24 global blocks, the
part compression changes) with head dimension 64 (embed 256, 4 heads by default),
images of 168 x 224 (a 12 x 16 patch grid), S frames. The trunk runs exactly as
`rvggt_jax.model.aggregator.aggregator_forward` runs it after the patch embed (frame block,
then `compression.global_block` or the dense block), keeping the layers the heads read;
the tokens and the saliency Psi are random inputs. The DINO patch embed and the heads
are not included: they are the same for every preset (the cost model reports the
speedup with the patch embed too, `predicted_speedup_with_patch_embed`).

For every S: each preset is compiled (trace + XLA compile time), then run `--repeats`
times with the presets interleaved (the order rotates every round); the table gives the
median and minimum wall time, the median process CPU time (user + system of all
threads: robust when other jobs share the cores), the speedups over dense (median wall,
CPU), the cost model's predicted speedup (`rvggt_jax.cost_report`, same trunk),
measured/predicted (median wall), XLA's temp buffer size, the process' peak RSS growth
while compiling and first running that preset, and (`--fill`) the measured fill of the
K/V slots next to the cost model's expectation.

    python benchmarks/bench_regime.py                                   # S = 8 16 32 64
    python benchmarks/bench_regime.py --frames 16 --presets dense regime --repeats 3
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402
from rvggt_jax import compression  # noqa: E402

from rvggt_jax.model import layers
from rvggt_jax.compression import PRESETS  # noqa: E402
from rvggt_jax.config import DinoConfig, VGGTConfig  # noqa: E402
from rvggt_jax.planning.cost import cost_report  # noqa: E402

KEEP = (4, 11, 17, 23)


def random_block(key, c: int, mlp_ratio: float, heads: int, ls: float = 0.1) -> dict:
    """One transformer block's params in our layout, N(0, 1/fan_in) weights."""
    hidden = int(c * mlp_ratio)
    d = c // heads
    ks = iter(jax.random.split(key, 16))

    def lin(i, o):
        return {"kernel": jax.random.normal(next(ks), (i, o), jnp.float32) / np.sqrt(i),
                "bias": 0.02 * jax.random.normal(next(ks), (o,), jnp.float32)}

    def ln(n):
        return {"scale": jnp.ones((n,), jnp.float32), "bias": jnp.zeros((n,), jnp.float32)}

    return {"norm1": ln(c), "attn": {"q": lin(c, c), "k": lin(c, c), "v": lin(c, c), "q_norm": ln(d),
                                     "k_norm": ln(d), "proj": lin(c, c)},
            "ls1": {"gamma": jnp.full((c,), ls, jnp.float32)}, "norm2": ln(c),
            "mlp": {"fc1": lin(c, hidden), "fc2": lin(hidden, c)}, "ls2": {"gamma": jnp.full((c,), ls, jnp.float32)}}


def random_trunk_params(config: VGGTConfig, seed: int = 0) -> dict:
    key = jax.random.PRNGKey(seed)
    kf, kg = jax.random.split(key)
    c, m, hd = config.embed_dim, config.mlp_ratio, config.num_heads
    return {"frame_blocks": {str(i): random_block(jax.random.fold_in(kf, i), c, m, hd) for i in range(config.depth)},
            "global_blocks": {str(i): random_block(jax.random.fold_in(kg, i), c, m, hd) for i in range(config.depth)}}


def trunk_forward(params, tokens: jax.Array, saliency: jax.Array, config: VGGTConfig,
                  grid_hw: tuple[int, int]) -> dict[int, jax.Array]:
    """tokens [B, S, P, C], saliency [B, S, h*w] -> {layer: [B, S, P, 2C]} for KEEP, as the
    aggregator computes them after the patch embed."""
    b, s, p, c = tokens.shape
    h, w = grid_hw
    frame_pos = jnp.asarray(layers.patch_positions(h, w, config.patch_start_idx))[None]
    global_pos = jnp.tile(frame_pos, (1, s, 1))
    geom = compression.Geometry(s, h, w, config.patch_start_idx)
    state = None if config.compression.is_dense else compression.init_state(config.compression, saliency, geom)
    x = tokens.reshape(b * s, p, c)
    out = {}
    for i in range(config.depth):
        x = layers.sequence_block(params["frame_blocks"][str(i)], x.reshape(b * s, p, c), frame_pos,
                                  layers.BlockConfig(config.num_heads, rope_freq=config.rope_freq))
        frame_out = x
        x = x.reshape(b, s * p, c)
        pg = params["global_blocks"][str(i)]
        if state is None:
            x = layers.sequence_block(pg, x, global_pos, layers.BlockConfig(config.num_heads, rope_freq=config.rope_freq))
        else:
            x, state = compression.global_block(pg, x, global_pos, i, config, state)
        if i in KEEP:
            out[i] = jnp.concatenate([frame_out.reshape(b, s, p, c), x.reshape(b, s, p, c)], axis=-1)
    return out


def kv_fill(config: VGGTConfig, tokens, saliency, params, grid_hw) -> float:
    """Measured fraction of the K/V slots attended that hold a key (filled / attended)
    over all compressed global layers of one forward: the dynamic slots' validity is read
    from the state (cached matches) or recomputed exactly as the block does (uncached).
    A merging layer attends with its capacity (`n_dyn_cap` dynamic slots) unless the
    sequence fills more (then with all `n_dyn`: such layers are printed)."""
    if config.compression.is_dense:
        return 1.0
    from rvggt_jax.compression import kv as kv_lib
    from rvggt_jax.compression import merge as merge_lib
    from rvggt_jax.compression.plan import layer_plan

    h, w = grid_hw
    b, s, p, c = tokens.shape
    ns = config.patch_start_idx
    cc = config.compression
    geom = compression.Geometry(s, h, w, ns)
    plans = [layer_plan(cc, i, geom) for i in range(config.depth)]

    @jax.jit
    def run(params, tokens, saliency):
        frame_pos = jnp.asarray(layers.patch_positions(h, w, ns))[None]
        global_pos = jnp.tile(frame_pos, (1, s, 1))
        state = compression.init_state(cc, saliency, geom)
        x = tokens.reshape(b * s, p, c)
        filled = []
        for i, plan in enumerate(plans):
            x = layers.sequence_block(params["frame_blocks"][str(i)], x.reshape(b * s, p, c), frame_pos,
                                      layers.BlockConfig(config.num_heads, rope_freq=config.rope_freq)).reshape(b, s * p, c)
            pg = params["global_blocks"][str(i)]
            dyn = plan.kind == "merge" and plan.kv_mode == "select"
            if dyn and plan.match_key is None:
                metric = x if plan.metric == "input" else layers.layer_norm(pg["norm1"], x)
                prot = state.protected
                src_pos = plan.partition.src_pos
                match = merge_lib.compute_match(
                    metric, None if prot is None else jnp.take(prot, src_pos, axis=1), plan, cc.match_chunk)
                _, ok = kv_lib.dynamic_slots(plan, cc, match, prot)
            x, state = compression.global_block(pg, x, global_pos, i, config, state)
            if dyn and plan.match_key is not None:
                ok = state.kv[plan.match_key, plan.tile].valid
            if dyn:
                filled.append((plan.n_fixed + jnp.sum(ok) / b, jnp.max(jnp.sum(ok, axis=1))))
            elif plan.kind in ("merge", "kv"):
                filled.append((jnp.float32(plan.n_kv), jnp.int32(0)))
        return filled

    filled, total = 0.0, 0
    for plan, (f, most) in zip([pl for pl in plans if pl.kind in ("merge", "kv")], run(params, tokens, saliency)):
        filled += float(f)
        over = int(most) > plan.n_dyn_cap
        if over:
            print(f"  layer {plan.layer}: {int(most)} dynamic K/V slots filled, over its capacity {plan.n_dyn_cap} "
                  f"(attends with all {plan.n_dyn})", flush=True)
        total += plan.n_kv if over else plan.n_kv_cap
    return filled / total if total else 1.0


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[8, 16, 32, 64])
    ap.add_argument("--presets", nargs="+", default=["dense", "regime", "regime_paper", "regime_local", "fastvggt",
                                                     "avggt"])
    ap.add_argument("--height", type=int, default=168)
    ap.add_argument("--width", type=int, default=224)
    ap.add_argument("--embed-dim", type=int, default=256)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fill", action="store_true", help="also measure the K/V slot fill (one extra compile per preset)")
    ap.add_argument("--out", type=str, default=None, help="append the markdown table to this file")
    args = ap.parse_args(argv)
    rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
    rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs
    for name in args.presets:
        if name not in PRESETS:
            raise SystemExit(f"unknown preset {name}; known: {PRESETS}")
    if "dense" not in args.presets:
        args.presets = ["dense"] + list(args.presets)

    base = VGGTConfig(embed_dim=args.embed_dim, num_heads=args.heads, depth=24,
                      dino=DinoConfig(depth=1, num_heads=args.heads)).validate()
    ps = base.patch_size
    h, w = args.height // ps, args.width // ps
    params = random_trunk_params(base)
    rows = []
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} cpus; embed {args.embed_dim}, "
          f"{args.heads} heads (head dim {args.embed_dim // args.heads}), {args.height}x{args.width}", flush=True)
    for s in args.frames:
        rng = np.random.default_rng(s)
        p = base.patch_start_idx + h * w
        tokens = jnp.asarray(rng.standard_normal((1, s, p, args.embed_dim), dtype=np.float32))
        sal = rng.random((1, s, h * w), dtype=np.float32) ** 4
        saliency = jnp.asarray(sal / sal.sum(-1, keepdims=True))
        compiled, info = {}, {}
        for name in args.presets:
            cfg = base.with_compression(name)
            rss0 = peak_rss_mb()
            t0 = time.perf_counter()
            fn = jax.jit(lambda pr, tk, sl, cfg=cfg: trunk_forward(pr, tk, sl, cfg, (h, w)))
            comp = fn.lower(params, tokens, saliency).compile()
            t_compile = time.perf_counter() - t0
            jax.block_until_ready(comp(params, tokens, saliency))  # warm-up
            mem = comp.memory_analysis()
            temp_mb = getattr(mem, "temp_size_in_bytes", 0) / 2 ** 20 if mem is not None else float("nan")
            compiled[name] = comp
            rep = cost_report(cfg, s, args.height, args.width)
            info[name] = dict(compile=t_compile, temp_mb=temp_mb, rss_growth=peak_rss_mb() - rss0,
                              predicted=rep["predicted_speedup"], times=[], cpu=[],
                              fill=kv_fill(cfg, tokens, saliency, params, (h, w)) if args.fill else float("nan"),
                              fill_expected=rep["kv_fill_expected"])
            print(f"S={s:3d} {name:14s} compiled in {t_compile:6.1f}s, temp {temp_mb:8.1f} MiB", flush=True)
        order = list(args.presets)
        for r in range(args.repeats):
            for name in order:
                c0 = time.process_time()
                t0 = time.perf_counter()
                jax.block_until_ready(compiled[name](params, tokens, saliency))
                info[name]["times"].append(time.perf_counter() - t0)
                info[name]["cpu"].append(time.process_time() - c0)
            print(f"S={s:3d} round {r + 1}: " + ", ".join(f"{n} {info[n]['times'][-1]:.2f}s" for n in order),
                  flush=True)
            order = order[1:] + order[:1]
        t_dense = statistics.median(info["dense"]["times"])
        c_dense = statistics.median(info["dense"]["cpu"])
        for name in args.presets:
            i = info[name]
            t = statistics.median(i["times"])
            c = statistics.median(i["cpu"])
            sp = t_dense / t
            rows.append(dict(S=s, preset=name, compile=i["compile"], median=t, min=min(i["times"]), cpu=c,
                             speedup=sp, speedup_cpu=c_dense / c, predicted=i["predicted"],
                             eff=sp / i["predicted"], temp_mb=i["temp_mb"], rss=i["rss_growth"], fill=i["fill"],
                             fill_expected=i["fill_expected"]))
        del compiled

    header = ("| S | preset | compile s | wall median s | wall min s | CPU median s | speedup (wall) "
              "| speedup (CPU) | predicted | measured/predicted | XLA temp MiB | peak RSS growth MiB "
              "| K/V fill (measured / expected) |\n"
              "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    lines = [header]
    for r in rows:
        fill = "" if np.isnan(r["fill"]) else f"{r['fill']:.2f} / {r['fill_expected']:.2f}"
        lines.append(f"| {r['S']} | {r['preset']} | {r['compile']:.1f} | {r['median']:.2f} | {r['min']:.2f} "
                     f"| {r['cpu']:.2f} | {r['speedup']:.2f}x | {r['speedup_cpu']:.2f}x | {r['predicted']:.2f}x "
                     f"| {r['eff']:.2f} | {r['temp_mb']:.0f} | {r['rss']:.0f} | {fill} |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        cmd = "python benchmarks/bench_regime.py " + " ".join(argv if argv is not None else sys.argv[1:])
        with open(args.out, "a") as f:
            f.write(f"\n`{cmd}`\n\n{table}\n")


if __name__ == "__main__":
    main()
