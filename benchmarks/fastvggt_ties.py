"""FastVGGT's merge decisions against ours on the same features, layer by layer.

Runs FastVGGT once with `peer_worker.py --trace-layer -2` on the checkpoint and images
that `bench_peers.py --keep <folder>` left (unless <folder>/trace_<S>.npz exists); for every global layer, the features FastVGGT matched on (its
attention input, the block's norm1 output), its src / dst rows in its own order, and its
choice (torch.max over its dst order). On the same features it runs our matching
(`rvggt_jax.compression.matching.best_match`, dst in ascending position, first index on
ties) and a float64 reference, and reports where the dst choices differ and by how much
the two best cosines differ there. Also compares every global block's output with ours
(`--ours`: our forward's aggregated layers, written by this script).

    python benchmarks/fastvggt_ties.py --work /tmp/bp16 --frames 16 \
        --torch-python /tmp/torchvenv/bin/python --fastvggt-src /tmp/peers/fastvggt
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402
from rvggt_jax.compression.matching import best_match  # noqa: E402
from rvggt_jax.compression.partition import Geometry, partition, stride_protected  # noqa: E402


def locate(rows: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """Positions of FastVGGT's (unit) rows among the unit feature rows: nearest by cosine."""
    out = np.empty(len(rows), np.int64)
    for s in range(0, len(rows), 1024):
        out[s:s + 1024] = np.argmax(rows[s:s + 1024] @ unit.T, axis=1)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="bench_peers.py --keep folder holding trace_<S>.npz")
    ap.add_argument("--frames", type=int, required=True)
    ap.add_argument("--layers", type=int, nargs="*", default=None)
    ap.add_argument("--torch-python", default="/tmp/torchvenv/bin/python")
    ap.add_argument("--fastvggt-src", default="/tmp/peers/fastvggt")
    args = ap.parse_args(argv)
    S, work = args.frames, Path(args.work)
    if not (work / f"trace_{S}.npz").exists():
        from benchmarks.bench_peers import Peer

        peer = Peer(args.torch_python, "fastvggt", args.fastvggt_src, work, work / f"images_{S}.npy", 2,
                    work / f"dst_{S}.npy", trace_layer=-2)
        peer.run(work / f"trace_{S}.npz")
        peer.close()
    t = np.load(work / f"trace_{S}.npz")
    params, config = rvggt_jax.load_pretrained(work)
    hh, ww = 168 // config.patch_size, 224 // config.patch_size
    P = 5 + hh * ww
    N = S * P
    part = partition(Geometry(S, hh, ww, 5), 33)
    prot = np.zeros(N, bool)
    prot[stride_protected(N, 0.1)] = True

    # our forward, every aggregated layer, on the same checkpoint and images
    cfg = dataclasses.replace(config, enable_point=False).with_compression(
        "fastvggt", duplicate_protected=True).with_outputs(layers=tuple(range(config.depth)))
    p = {k: v for k, v in params.items() if k != "point_head"}
    out = jax.jit(rvggt_jax.rvggt_forward)(p, np.load(work / f"images_{S}.npy"), cfg)
    C = config.embed_dim
    for i in (args.layers if args.layers is not None else range(config.depth)):
        theirs = t[f"trace_glob{i}"].reshape(N, C)
        ours = np.asarray(out[f"aggregated_{i:02d}"])[0, :, :, C:].reshape(N, C)
        d = np.abs(ours - theirs).max(-1) / np.abs(theirs).max()
        bad = d > 1e-4
        per_frame = bad.reshape(S, P).any(1)
        metric = t[f"trace_metric{i}"][0].astype(np.float32)
        unit = metric / np.linalg.norm(metric, axis=-1, keepdims=True)
        a_pos, b_pos = locate(t[f"trace_a{i}"][0], unit), locate(t[f"trace_b{i}"][0], unit)
        theirs_dst = b_pos[t[f"trace_node_idx{i}"][0]]
        # ours on the same features: src / dst in ascending position
        _, arg = best_match(jax.numpy.asarray(metric[None]), part.src_pos[None], part.dst_pos[None])
        ours_dst_by_src = dict(zip(part.src_pos.tolist(), part.dst_pos[np.asarray(arg)[0, 0]].tolist()))
        ours_dst = np.array([ours_dst_by_src[int(s)] for s in a_pos])
        u64 = metric.astype(np.float64)
        u64 /= np.linalg.norm(u64, axis=-1, keepdims=True)
        differ = np.flatnonzero(ours_dst != theirs_dst)
        order_sorted = bool(np.all(np.diff(a_pos) > 0) and np.all(np.diff(b_pos) > 0))
        print(f"layer {i:2d}: max rel diff {d.max():.1e}; outputs differ (>1e-4 rel) at {bad.sum()} tokens in {per_frame.sum()} frames "
              f"({bad[part.is_dst & prot].sum()} of them protected dst, {(bad & ~(part.is_dst & prot)).sum()} others); "
              f"dst choices differ for {differ.size} of {a_pos.size} src; FastVGGT's src/dst order ascending: {order_sorted}",
              flush=True)
        for j in differ[:8]:
            s_, o_, th_ = a_pos[j], ours_dst[j], theirs_dst[j]
            c_o, c_t = u64[s_] @ u64[o_], u64[s_] @ u64[th_]
            c32_o, c32_t = unit[s_] @ unit[o_], unit[s_] @ unit[th_]
            print(f"    src {s_} (frame {s_ // P}): ours dst {o_} (frame {o_ // P}), theirs dst {th_} (frame {th_ // P}); "
                  f"cos f64 {c_o:.10f} vs {c_t:.10f} (diff {c_o - c_t:.1e}); f32 {c32_o:.8f} vs {c32_t:.8f}; "
                  f"protected src {prot[s_]}; identical dst rows {np.array_equal(metric[o_], metric[th_])}")


if __name__ == "__main__":
    main()
