"""How far upstream PyTorch VGGT moves under its own bfloat16 mixed precision.

Reference for the tolerance of rvggt-jax's bfloat16 mode: upstream's demo runs
`with torch.cuda.amp.autocast(dtype=torch.bfloat16): model(images)`, and `VGGT.forward`
switches autocast off again around the camera, depth and point heads. Here, on CPU:

- the aggregator runs under `torch.autocast("cpu", dtype=torch.bfloat16)`;
- the camera / depth / point heads run outside autocast, in float32, on the aggregator's
  outputs cast to float32 (upstream's `torch.cuda.amp.autocast(enabled=False)` does not
  switch *CPU* autocast off, so the heads are called outside the context explicitly);
- the track head stays under autocast, as in `VGGT.forward` (it sits outside the
  `enabled=False` block there); rows `*_f32head` run it in float32 instead.

Metric (as tests/helpers/metrics.py): rel_err = max|bf16 - f32| / max|f32| per output. Inputs:
the fixture's images (reference: its float32 golden outputs) and two more with uniform
noise added to the images (seeds 1, 2; reference: upstream's float32 run on them).
Layouts: `tiny`, the fixture checkpoint (tests/data/vggt_tiny), and `wide`, a fresh
random upstream model with embed_dim 128 / 4 heads (same depth 24, `build_upstream`).

A second variant (`*_fp32_layernorm`) emulates CUDA autocast's fp32 policy for
layer_norm / group_norm: CPU autocast runs LayerNorm in the input's dtype, so the
aggregator's q/k norms output bfloat16 and RoPE's cos/sin are computed in bfloat16; on
CUDA those norms run (and return) float32, RoPE runs in float32 and SDPA casts to bf16.

    pip install torch==2.13.0 huggingface_hub einops   # benchmark-only dependencies
    python benchmarks/upstream_bf16.py --vggt-src /path/to/vggt --out bf16.json

Upstream code is imported from --vggt-src at run time only (benchmarks/upstream.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.upstream import build_upstream  # noqa: E402
from rvggt_jax.config import VGGTConfig  # noqa: E402

TINY = ROOT / "tests" / "data" / "vggt_tiny"
SEEDS = (0, 1, 2)  # 0: the fixture's images; 1, 2: images + U(-NOISE, NOISE), clipped to [0, 1]
NOISE = 0.02
SANITY_TOL = 1e-5  # float32 upstream vs the golden outputs (track keys: reported only)
TRACK_KEYS = ("track", "vis", "conf")


def rel_err(ours, ref) -> float:
    """max |ours - ref| / max |ref| (tests/helpers/metrics.py's metric)."""
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape, (ours.shape, ref.shape)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())


def bf16_autocast(enabled: bool):
    import torch

    return torch.autocast("cpu", dtype=torch.bfloat16) if enabled else nullcontext()


@contextmanager
def fp32_norms():
    """LayerNorm / GroupNorm as CUDA autocast runs them: inputs cast to float32, float32 out."""
    import torch
    import torch.nn.functional as F

    ln, gn = torch.nn.LayerNorm.forward, torch.nn.GroupNorm.forward

    def layer_norm(self, x):
        if torch.is_autocast_enabled("cpu") and x.dtype != torch.float32:
            with torch.autocast("cpu", enabled=False):
                return F.layer_norm(x.float(), self.normalized_shape, self.weight, self.bias, self.eps)
        return ln(self, x)

    def group_norm(self, x):
        if torch.is_autocast_enabled("cpu") and x.dtype != torch.float32:
            with torch.autocast("cpu", enabled=False):
                return F.group_norm(x.float(), self.num_groups, self.weight, self.bias, self.eps)
        return gn(self, x)

    torch.nn.LayerNorm.forward, torch.nn.GroupNorm.forward = layer_norm, group_norm
    try:
        yield
    finally:
        torch.nn.LayerNorm.forward, torch.nn.GroupNorm.forward = ln, gn


def run(model, images, query_points, bf16: bool, cuda_norms: bool = False) -> dict:
    """VGGT.forward step by step (eval mode), with the aggregator under CPU bf16 autocast.

    Returns float32 numpy outputs plus "_token_dtypes" (the aggregator outputs' dtypes)."""
    import torch

    norms = fp32_norms() if cuda_norms else nullcontext()
    out = {}
    with torch.no_grad(), norms:
        with bf16_autocast(bf16):
            tokens, start = model.aggregator(images)
        dtypes = {str(t.dtype) for t in tokens}
        tokens = [t.float() for t in tokens]
        for i, t in enumerate(tokens):
            out[f"aggregated_{i:02d}"] = t
        # upstream: `with torch.cuda.amp.autocast(enabled=False):` -> float32 heads
        pose_list = model.camera_head(tokens)
        out["pose_enc"], out["pose_enc_list"] = pose_list[-1], torch.stack(pose_list)
        out["depth"], out["depth_conf"] = model.depth_head(tokens, images=images, patch_start_idx=start)
        out["world_points"], out["world_points_conf"] = model.point_head(
            tokens, images=images, patch_start_idx=start)
        # upstream: the track head is outside that block, i.e. under the caller's autocast
        with bf16_autocast(bf16):
            tracks, vis, conf = model.track_head(tokens, images=images, patch_start_idx=start,
                                                 query_points=query_points)
        out["track"], out["vis"], out["conf"] = tracks[-1], vis, conf
        if bf16:
            tracks, vis, conf = model.track_head(tokens, images=images, patch_start_idx=start,
                                                 query_points=query_points)
            out["track_f32head"], out["vis_f32head"], out["conf_f32head"] = tracks[-1], vis, conf
    out = {k: v.float().numpy() for k, v in out.items()}
    out["_token_dtypes"] = dtypes
    return out


def upstream_forward(model, images, query_points) -> dict[str, np.ndarray]:
    """Upstream's own VGGT.forward in float32 (the reference for the noisy inputs)."""
    import torch

    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # torch.cuda.amp.autocast(enabled=False)
        pred = model(images, query_points=query_points)
    out = {k: v for k, v in pred.items() if k not in ("images", "pose_enc_list")}
    out["pose_enc_list"] = torch.stack(pred["pose_enc_list"])
    with torch.no_grad():
        tokens, _ = model.aggregator(images)
    out.update({f"aggregated_{i:02d}": t for i, t in enumerate(tokens)})
    return {k: v.float().numpy() for k, v in out.items()}


def inputs(golden, seed: int):
    import torch

    images = torch.from_numpy(golden["images"].copy())
    if seed:
        g = torch.Generator().manual_seed(seed)
        images = (images + NOISE * (2 * torch.rand(images.shape, generator=g) - 1)).clamp(0, 1)
    return images, torch.from_numpy(golden["query_points"].copy())


def wide_config(tiny: VGGTConfig) -> VGGTConfig:
    return dataclasses.replace(
        tiny, embed_dim=128, num_heads=4, dino=dataclasses.replace(tiny.dino, num_heads=4),
        dpt_head=dataclasses.replace(tiny.dpt_head, features=32, out_channels=(16, 32, 64, 64)),
    ).validate()


def measure(name, model, golden, sanity: bool):
    """{variant: {output: [rel_err per seed]}} for the plain CPU autocast and fp32 norms."""
    errs: dict[str, dict[str, list[float]]] = {"cpu_autocast": {}, "fp32_layernorm": {}}
    for seed in SEEDS:
        images, qp = inputs(golden, seed)
        t0 = time.perf_counter()
        f32 = upstream_forward(model, images, qp)
        mine = run(model, images, qp, bf16=False)
        gap = max(rel_err(mine[k], f32[k]) for k in f32)
        if gap != 0.0:
            raise SystemExit(f"the step-by-step forward differs from VGGT.forward by {gap:.1e}")
        if seed == 0 and sanity:
            print(f"[{name}] float32 upstream vs golden outputs:")
            bad = []
            for k in f32:
                e = rel_err(f32[k], golden[k])
                print(f"  {k:18s} {e:.1e}")
                if e > SANITY_TOL and k not in TRACK_KEYS:
                    bad.append(k)
            if bad:
                raise SystemExit(f"float32 upstream does not reproduce the golden {bad}")
            ref = {k: golden[k] for k in f32}  # the fixture's float32 golden outputs
        else:
            ref = f32
        for variant in errs:
            bf = run(model, images, qp, bf16=True, cuda_norms=variant == "fp32_layernorm")
            if seed == 0:
                print(f"[{name}/{variant}] aggregator output dtypes under autocast: {bf['_token_dtypes']}")
            for k, v in bf.items():
                if k.startswith("_"):
                    continue
                errs[variant].setdefault(k, []).append(rel_err(v, ref[k.removesuffix("_f32head")]))
        print(f"[{name}] seed {seed}: {time.perf_counter() - t0:.1f} s")
    return errs


def table(name: str, errs) -> str:
    main, cuda = errs["cpu_autocast"], errs["fp32_layernorm"]
    lines = [f"**{name}** (rel_err of bf16 vs float32; seeds 0 = fixture images, 1-2 = + noise)", "",
             "| output | seed 0 | seed 1 | seed 2 | **max** | max, fp32 LayerNorm |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for k, v in main.items():
        cells = " | ".join(f"{e:.1e}" for e in v)
        lines.append(f"| {k} | {cells} | **{max(v):.1e}** | {max(cuda[k]):.1e} |")
    return "\n".join(lines)


def summary(all_errs: dict) -> str:
    """Both layouts side by side: the fixture input, and the max over the three inputs."""
    names = list(next(iter(all_errs.values()))["cpu_autocast"])
    head = ["output"]
    for layout in all_errs:
        head += [f"{layout}: fixture input", f"{layout}: **max of 3**"]
    head += [f"{layout}: max, fp32 LayerNorm" for layout in all_errs]
    lines = ["| " + " | ".join(head) + " |", "| --- |" + " ---: |" * (len(head) - 1)]
    for k in names:
        cells = []
        for errs in all_errs.values():
            v = errs["cpu_autocast"][k]
            cells += [f"{v[0]:.1e}", f"**{max(v):.1e}**"]
        cells += [f"{max(errs['fp32_layernorm'][k]):.1e}" for errs in all_errs.values()]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--vggt-src", required=True, help="folder holding the upstream vggt/ package")
    p.add_argument("--out", help="write {layout: {output: max rel_err}} JSON here")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--layouts", nargs="+", default=["tiny", "wide"], choices=["tiny", "wide"])
    args = p.parse_args(argv)

    import torch
    from safetensors.numpy import load_file
    from safetensors.torch import load_file as load_torch

    torch.set_num_threads(args.threads)
    golden = load_file(TINY / "io.safetensors")
    tiny = VGGTConfig.from_json(TINY / "config.json")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s)")

    results, tables, all_errs = {}, [], {}
    for layout in args.layouts:
        if layout == "tiny":
            model = build_upstream(tiny, args.vggt_src)
            missing = model.load_state_dict(load_torch(str(TINY / "model.safetensors")), strict=True)
            print(f"[tiny] strict load of model.safetensors: {missing}")
        else:
            cfg = wide_config(tiny)
            model = build_upstream(cfg, args.vggt_src)
            print(f"[wide] random upstream model: embed_dim {cfg.embed_dim}, {cfg.num_heads} heads, depth "
                  f"{cfg.depth}, DPT features {cfg.dpt_head.features}")
        errs = measure(layout, model, golden, sanity=layout == "tiny")
        for variant, suffix in (("cpu_autocast", ""), ("fp32_layernorm", "_fp32_layernorm")):
            results[layout + suffix] = {k: max(v) for k, v in errs[variant].items()}
        tables.append(table(layout, errs))
        all_errs[layout] = errs

    print()
    print("\n\n".join(tables))
    print("\n**summary** (rel_err of bf16 vs float32)\n")
    print(summary(all_errs))
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
