"""One PyTorch peer of `bench_peers.py`, run in a Python that has torch (not the project's).

Started by bench_peers.py as a subprocess; it never imports jax or rvggt_jax (the config
comes as the checkpoint's config.json). Peers:

  upstream  the upstream VGGT package (facebookresearch/vggt or the xianglic/vggt snapshot)
  fastvggt  FastVGGT's code (mystorm16/FastVGGT): merging in every global layer
  regime    the RegimeVGGT authors' code (Brandon-Z-226/RegimeVGGT: methods/ and the vggt/
            files it overlays on upstream VGGT), run as their eval scripts run it:
            `methods.regimevggt.run_aggregator_regimevggt(model, images, **HYBRID_CONFIG)`,
            then the camera and depth heads

`--build` writes the random checkpoint (upstream's modules, `benchmarks/upstream.py`'s
draw) and exits. Otherwise the worker loads the checkpoint and answers one JSON command per
line on stdin ({"cmd": "run", "save": path|null} -> {"seconds": t}; {"cmd": "quit"}).

Changes a peer needs to run on CPU in float32, applied at runtime (its files are not
edited), are listed in CPU_CHANGES and printed on start.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import types
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CPU_CHANGES = {
    "upstream": [
        "none: upstream runs on CPU in float32 as written (no autocast is entered by the model)",
    ],
    "fastvggt": [
        "vggt/models/aggregator.py: its module-level `torch` is seen through a shim in which "
        "torch.bfloat16 is torch.float32 (the explicit .to(torch.bfloat16) casts of images, "
        "tokens, special tokens, the normalisation buffers and the DPT intermediates keep "
        "float32), torch.cuda.synchronize/empty_cache are no-ops (per-layer synchronisation), "
        "and device='cuda' arguments (torch.zeros, PositionGetter) become the CPU",
        "merging/merge.py: fast_similarity_chunks (torch.jit.script, casts a and b to bfloat16 "
        "for the similarity bmm) replaced by the same chunked bmm + max in float32",
        "merging/merge.py: torch.randint of the per-cell dst choice returns our draw "
        "(rvggt_jax.compression.partition.dst_cells with seed 33, passed as a file) so that "
        "both pick the same dst patches; FastVGGT's own draw is torch.Generator seeded 33",
        "model built with the checkpoint's sizes (upstream.build_upstream with FastVGGT's "
        "modules), DPT head indices [0, 1, 2, 3] into its 4 kept layers, point head off "
        "(FastVGGT's VGGT() default enable_point=False), update_patch_dimensions(w, h) as "
        "its demo calls",
    ],
    "regime": [
        "methods/regimevggt.py: its module-level `torch` is seen through the shim above "
        "(torch.bfloat16 is torch.float32: the DPT intermediates' .to(torch.bfloat16) keeps "
        "float32; the per-layer torch.cuda.synchronize/empty_cache are no-ops)",
        "vggt/models/aggregator.py: its module-level `torch` through the same shim, so the "
        "normalisation buffers _resnet_mean/_resnet_std that Aggregator.__init__ registers "
        "are float32 (theirs: bfloat16, e.g. 0.484375 for 0.485; run_aggregator_regimevggt "
        "normalises the images with them)",
        "methods/fastvggt_merge.py: fast_similarity_chunks (torch.jit.script, bfloat16 bmm) "
        "replaced by the same chunked bmm + max in float32",
        "methods/fastvggt_merge.py: torch.randint of the per-cell dst choice returns our draw "
        "(rvggt_jax.compression.partition.dst_cells with seed 33, passed as a file) so that "
        "both pick the same dst patches; theirs is torch.Generator seeded 33 in every layer",
        "matplotlib (imported by vggt/layers/attention.py for its attention-map plots, off) "
        "stubbed when not installed",
        "model built with the checkpoint's sizes (upstream.build_upstream with their modules), "
        "DPT head indices [0, 1, 2, 3] into the 4 layers their aggregator keeps ([4, 11, 17, 23]), "
        "point head not run (their eval scripts run the camera and depth heads only), "
        "every attention layer's patch_width/patch_height set to the image's patch grid "
        "(what FastVGGT's model.update_patch_dimensions, called by their eval, does)",
        "configuration: HYBRID_CONFIG read from their eval/eval_scannet50.py, passed as their "
        "eval passes it",
    ],
}


def _ns(d):
    if isinstance(d, dict):
        return types.SimpleNamespace(**{k: _ns(v) for k, v in d.items()})
    return d


def load_config(folder: Path):
    c = _ns(json.loads((folder / "config.json").read_text()))
    c.dpt_head.out_channels = tuple(c.dpt_head.out_channels)
    c.dpt_head.intermediate_layer_idx = tuple(c.dpt_head.intermediate_layer_idx)
    c.head_dim = c.embed_dim // c.num_heads
    return c


class _NoCuda:
    @staticmethod
    def synchronize(*a, **k):
        return None

    @staticmethod
    def empty_cache(*a, **k):
        return None

    @staticmethod
    def is_available():
        return False


class _TorchF32:
    """The `torch` module, except bfloat16 -> float32, no cuda, device='cuda' -> cpu."""

    def __init__(self, torch, randint=None):
        self._torch = torch
        self._randint = randint

    def __getattr__(self, name):
        t = self._torch
        if name == "bfloat16":
            return t.float32
        if name == "cuda":
            return _NoCuda
        if name == "randint" and self._randint is not None:
            return self._randint
        attr = getattr(t, name)
        if name in ("zeros", "ones", "empty", "arange", "full", "tensor"):
            def on_cpu(*a, __f=attr, **k):
                if str(k.get("device", "cpu")).startswith("cuda"):
                    k["device"] = "cpu"
                return __f(*a, **k)
            return on_cpu
        return attr


def _similarity_f32(a, b_transposed, chunk_size: int):
    """FastVGGT's fast_similarity_chunks in float32 (theirs casts a and b to bfloat16)."""
    import torch

    B, num_src, _ = a.shape
    node_max = torch.empty(B, num_src, dtype=a.dtype)
    node_idx = torch.empty(B, num_src, dtype=torch.long)
    for i in range(0, num_src, chunk_size):
        end_i = min(i + chunk_size, num_src)
        scores = torch.bmm(a[:, i:end_i, :], b_transposed)
        m, idx = torch.max(scores, dim=2)
        node_max[:, i:end_i] = m
        node_idx[:, i:end_i] = idx
    return node_max, node_idx


def _diagnostic_keep_dst_rows(att_mod, torch):
    """Diagnosis only (env PEER_DIAG_DST_ROW_FOR_PROTECTED=1), not a CPU change: FastVGGT's
    unmerge writes the protected copies last, so a protected dst token takes its own
    unmerged query's output; this puts back its dst (group) row, as ours does, to show
    that this is the whole difference. The dst order is FastVGGT's own (the same argsort
    of the same idx_buffer_seq, rebuilt from the sets: -1 = dst, 0 = src)."""
    inner = att_mod.token_merge_bipartite2d

    def tm(metric, w, h, sx, sy, r, no_rand=False, generator=None, enable_protection=False):
        merge, unmerge = inner(metric, w, h, sx, sy, r, no_rand, generator, enable_protection)
        N = metric.shape[1]
        n_prot = int(N * 0.1)
        prot = torch.arange(0, N, max(1, N // n_prot))[:n_prot]

        def unmerge2(x):
            out = unmerge(x)
            dst_mask = _DIAG["is_dst"]
            seq = torch.where(torch.from_numpy(dst_mask), -1, 0).to(torch.int64)
            order = seq.reshape(1, -1, 1).argsort(dim=1)[0, :, 0]
            b_idx = order[: int(dst_mask.sum())]
            rank = torch.full((N,), -1, dtype=torch.long)
            rank[b_idx] = torch.arange(b_idx.numel())
            unm_len = x.shape[1] - b_idx.numel() - n_prot
            pd = prot[rank[prot] >= 0]
            out[:, pd] = x[:, unm_len + rank[pd]]
            return out

        return merge, unmerge2

    att_mod.token_merge_bipartite2d = tm


def _shared_draw(torch, dst_draw: np.ndarray | None):
    """torch.randint as the peer's merge calls it, except that the per-cell dst draw (a call
    of dst_draw's shape) returns our draw, so that both sides pick the same dst patches."""
    def randint(high, size=None, device=None, generator=None, **k):
        if dst_draw is not None and tuple(size) == tuple(dst_draw.shape):
            return torch.from_numpy(dst_draw.astype(np.int64))
        return torch.randint(high, size=size, generator=generator, **k)

    return randint


_DIAG: dict = {}


def build_fastvggt(config, src: Path, ckpt: Path, dst_draw: np.ndarray | None, w: int, h: int, trace: dict):
    import torch

    sys.path.insert(0, str(src))
    import merging.merge as mm
    import vggt.models.aggregator as agg_mod
    import vggt.layers.rope as rope_mod
    from vggt.models.vggt import VGGT

    from benchmarks.upstream import build_upstream

    randint = _shared_draw(torch, dst_draw)

    agg_mod.torch = _TorchF32(torch)
    mm.torch = _TorchF32(torch, randint)
    orig_sim = _similarity_f32
    layer_box = {"n": 0}

    def sim(a, bt, chunk_size):
        m, i = orig_sim(a, bt, chunk_size)
        n = layer_box["n"]
        if trace.get("layer") in (n, -2):
            trace[f"a{n}"] = a.detach().numpy().copy()
            trace[f"b{n}"] = bt.transpose(-1, -2).detach().numpy().copy()
            trace[f"node_max{n}"], trace[f"node_idx{n}"] = m.numpy().copy(), i.numpy().copy()
        layer_box["n"] += 1
        return m, i

    mm.fast_similarity_chunks = sim
    import vggt.layers.attention as att_mod

    orig_tm = att_mod.token_merge_bipartite2d

    def tm(metric, *a, **k):
        if trace.get("layer") in (layer_box["n"], -2):
            trace[f"metric{layer_box['n']}"] = metric.detach().numpy().copy()
        return orig_tm(metric, *a, **k)

    att_mod.token_merge_bipartite2d = tm
    if os.environ.get("PEER_DIAG_DST_ROW_FOR_PROTECTED") == "1":
        _diagnostic_keep_dst_rows(att_mod, torch)
    orig_call = rope_mod.PositionGetter.__call__

    def pos_call(self, batch_size, height, width, device):
        return orig_call(self, batch_size, height, width, "cpu")

    rope_mod.PositionGetter.__call__ = pos_call

    model = build_upstream(config, src)  # FastVGGT's modules (its vggt package is first on sys.path)
    from safetensors.torch import load_file

    state = load_file(str(ckpt / "model.safetensors"))
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing:
        raise SystemExit(f"fastvggt: parameters missing from the checkpoint: {missing[:5]}")
    model.point_head = None
    model.vis_attn_map = False  # set by its VGGT.__init__, which build_upstream bypasses
    model.depth_head.intermediate_layer_idx = [0, 1, 2, 3]
    VGGT.update_patch_dimensions(model, w, h)
    if trace.get("layer", -1) != -1:  # every global block's output, for a layer-by-layer comparison
        for i, blk in enumerate(model.aggregator.global_blocks):
            blk.register_forward_hook(lambda m, inp, out, i=i: trace.__setitem__(f"glob{i}", out.detach().numpy().copy()))
    model.eval()
    return model, layer_box


def hybrid_config(src: Path) -> tuple[dict, str]:
    """The authors' HYBRID_CONFIG, read (ast, not imported: the script imports FastVGGT's
    eval utilities) from <src>/eval/eval_scannet50.py (the configuration is theirs: this
    repository keeps no copy of it)."""
    import ast

    f = src / "eval" / "eval_scannet50.py"
    if not f.exists():
        raise SystemExit(f"{f} is missing: the regime peer reads the authors' HYBRID_CONFIG from it "
                         "(see docs/history/peers.md, 'Against the PyTorch peers', for the folder)")
    for node in ast.parse(f.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "HYBRID_CONFIG" for t in node.targets):
            call = node.value  # dict(key=literal, ...)
            return {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords}, str(f)
    raise SystemExit(f"{f} has no HYBRID_CONFIG")


def _stub_module(name: str):
    """An empty module standing in for an optional import that is never used."""
    import importlib.util

    parent = name.split(".")[0]
    if importlib.util.find_spec(parent) is not None:
        return
    for part in (parent, name):
        sys.modules.setdefault(part, types.ModuleType(part))
    setattr(sys.modules[parent], name.split(".")[-1], sys.modules[name])


def _closure(fn) -> dict:
    return dict(zip(fn.__code__.co_freevars, (c.cell_contents for c in fn.__closure__)))


def _regime_diagnostics(tm, S: int, h: int, w: int, alpha: float, torch):
    """Diagnosis only (environment variables), not CPU changes: wrap the authors'
    token_merge_bipartite2d so that one known difference from ours at a time is removed.

    (Both were our behaviour before 2026-12-04, when they explained the whole difference;
    ours now does as theirs, so with either switch the two differ again.)
    PEER_DIAG_STATIC_R=1: merge r = min(int(rho N), N_src - P_max) src, the static count,
      P_max = (S-1) max(1, int(alpha h w)); theirs merges min(int(rho N), N_src,
      unprotected src), more when protected patches fall on dst cells (rho 0.99).
      N_src is counted for an even patch grid (h, w even), as in the benchmark.
    PEER_DIAG_DST_ROW_FOR_PROTECTED=1: after their unmerge, a protected dst token takes its
      dst group's row instead of the output of its own un-merged query row."""
    static_r = os.environ.get("PEER_DIAG_STATIC_R") == "1"
    dst_row = os.environ.get("PEER_DIAG_DST_ROW_FOR_PROTECTED") == "1"
    if not (static_r or dst_row):
        return tm
    n_dst = (5 + h * w) + (S - 1) * (5 + (h // 2) * (w // 2))
    n_src = S * (5 + h * w) - n_dst
    p_max = (S - 1) * max(1, int(h * w * alpha))

    def wrapped(metric, w_, h_, sx, sy, r, *a, **k):
        if static_r:
            r = min(r, n_src - p_max)
        merge, unmerge = tm(metric, w_, h_, sx, sy, r, *a, **k)
        if not dst_row or not hasattr(unmerge, "size"):
            return merge, unmerge
        c = _closure(unmerge)
        N = c["N"]
        b = c["b_idx"][0, :, 0]
        prot = c["protected_idx"][0, :, 0]
        unm_len = c["unm_idx"].shape[1]
        rank = torch.full((N,), -1, dtype=torch.long)
        rank[b] = torch.arange(b.numel())
        pd = prot[rank[prot] >= 0]

        def unmerge2(x):
            out = unmerge(x)
            out[:, pd] = x[:, unm_len + rank[pd]]
            return out

        unmerge2.size, unmerge2.merged_global_idx = unmerge.size, unmerge.merged_global_idx
        return merge, unmerge2

    return wrapped


def build_regime(config, src: Path, ckpt: Path, dst_draw: np.ndarray | None, S: int, w: int, h: int,
                 trace: dict):
    """The authors' model and forward (their eval's `infer_regimevggt_and_reconstruct`, the
    model part): run_aggregator_regimevggt with HYBRID_CONFIG, camera head, depth head."""
    import torch

    _stub_module("matplotlib.pyplot")  # vggt/layers/attention.py plots attention maps (off)
    sys.path.insert(0, str(src))
    import methods.fastvggt_merge as fm
    import methods.regimevggt as rv
    import vggt.layers.attention as att_mod
    import vggt.models.aggregator as agg_mod

    from benchmarks.upstream import build_upstream

    randint = _shared_draw(torch, dst_draw)

    agg_mod.torch = _TorchF32(torch)
    rv.torch = _TorchF32(torch)
    fm.torch = _TorchF32(torch, randint)
    fm.fast_similarity_chunks = _similarity_f32
    cfg, cfg_from = hybrid_config(src)
    tm = _regime_diagnostics(fm.token_merge_bipartite2d, S, h, w, cfg.get("merge_alpha", 0.1), torch)
    rv.token_merge_bipartite2d = tm  # both call sites imported it by name
    att_mod.token_merge_bipartite2d = tm

    model = build_upstream(config, src)  # their modules (the folder's vggt package is first on sys.path)
    from safetensors.torch import load_file

    missing, _ = model.load_state_dict(load_file(str(ckpt / "model.safetensors")), strict=False)
    if missing:
        raise SystemExit(f"regime: parameters missing from the checkpoint: {missing[:5]}")
    model.point_head = None
    model.depth_head.intermediate_layer_idx = [0, 1, 2, 3]
    for m in model.aggregator.modules():  # FastVGGT's VGGT.update_patch_dimensions(w, h)
        if hasattr(m, "patch_width") and hasattr(m, "patch_height"):
            m.patch_width, m.patch_height = w, h
    model.eval()

    if trace.get("layer", -1) != -1:  # every global layer's output, for a layer-by-layer comparison
        blocks = list(model.aggregator.global_blocks)
        hybrid = rv._hybrid_global_forward

        def hybrid_traced(block, *a, **k):
            out = hybrid(block, *a, **k)
            trace[f"glob{blocks.index(block)}"] = out.detach().numpy().copy()
            return out

        rv._hybrid_global_forward = hybrid_traced
        for i, blk in enumerate(blocks):  # merge-only layers call the block itself
            blk.register_forward_hook(
                lambda m, inp, out, i=i: trace.__setitem__(f"glob{i}", out.detach().numpy().copy()))

    def forward(images):
        output_list, psi = rv.run_aggregator_regimevggt(model, images, **cfg)
        pose_enc = model.camera_head(output_list)[-1]
        depth, depth_conf = model.depth_head(output_list, images=images, patch_start_idx=psi)
        return {"pose_enc": pose_enc, "depth": depth, "depth_conf": depth_conf}

    return forward, cfg_from


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--kind", choices=("upstream", "fastvggt", "regime"), required=True)
    ap.add_argument("--src", required=True)
    ap.add_argument("--ckpt", required=True, help="folder: config.json (+ model.safetensors unless --build)")
    ap.add_argument("--build", action="store_true", help="write model.safetensors and exit (upstream)")
    ap.add_argument("--images", help=".npy [1, S, 3, H, W] float32")
    ap.add_argument("--dst-draw", help=".npy [S-1, h/2, w/2] int: dst cell choice (fastvggt, regime)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--trace-layer", type=int, default=-1, help="fastvggt: save the matching inputs and results of this global layer (-2: all) "
                    "and every global block's output; regime: any value but -1 saves every global layer's output")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    ckpt = Path(args.ckpt)
    config = load_config(ckpt)
    if args.build:
        from benchmarks.upstream import build_upstream, import_upstream

        import_upstream(args.src)
        model = build_upstream(config, args.src)
        from safetensors.torch import save_file

        save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(ckpt / "model.safetensors"))
        return

    images = torch.from_numpy(np.load(args.images))
    trace = {"layer": args.trace_layer}
    box = None
    extra = {}
    if args.kind == "upstream":
        from benchmarks.upstream import import_upstream
        from safetensors.torch import load_file

        import_upstream(args.src)
        from benchmarks.upstream import build_upstream

        model = build_upstream(config, args.src)
        model.load_state_dict(load_file(str(ckpt / "model.safetensors")))
        model.eval()
    elif args.kind == "regime":
        draw = np.load(args.dst_draw) if args.dst_draw else None
        h, w = images.shape[-2] // config.patch_size, images.shape[-1] // config.patch_size
        model, cfg_from = build_regime(config, Path(args.src), ckpt, draw, images.shape[1], w, h, trace)
        extra["config_from"] = cfg_from
    else:
        draw = np.load(args.dst_draw) if args.dst_draw else None
        if os.environ.get("PEER_DIAG_DST_ROW_FOR_PROTECTED") == "1":  # the dst set, from the draw
            S_, hh, ww = images.shape[1], images.shape[-2] // config.patch_size, images.shape[-1] // config.patch_size
            P_ = 5 + hh * ww
            is_dst = np.zeros(S_ * P_, bool)
            is_dst[:P_] = True
            for f in range(1, S_):
                is_dst[f * P_: f * P_ + 5] = True
                k = draw[f - 1]
                rows = (np.arange(hh // 2)[:, None] * 2 + k // 2)
                cols = (np.arange(ww // 2)[None, :] * 2 + k % 2)
                is_dst[f * P_ + 5 + (rows * ww + cols).ravel()] = True
            _DIAG["is_dst"] = is_dst
        h, w = images.shape[-2] // config.patch_size, images.shape[-1] // config.patch_size
        model, box = build_fastvggt(config, Path(args.src), ckpt, draw, w, h, trace)
    print(json.dumps({"ready": args.kind, "torch": torch.__version__, "threads": torch.get_num_threads(),
                      "cpu_changes": CPU_CHANGES[args.kind], **extra}), flush=True)

    for line in sys.stdin:
        cmd = json.loads(line)
        if cmd["cmd"] == "quit":
            break
        if box is not None:
            box["n"] = 0
        t = time.perf_counter()
        with torch.inference_mode():
            out = model(images)
        dt = time.perf_counter() - t
        if cmd.get("save"):
            keep = {k: v.float().numpy() for k, v in out.items()
                    if k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")}
            for k, v in trace.items():
                if k != "layer":
                    keep["trace_" + k] = v
            np.savez(cmd["save"], **keep)
        print(json.dumps({"seconds": dt}), flush=True)


if __name__ == "__main__":
    main()
