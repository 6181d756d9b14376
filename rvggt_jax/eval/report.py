"""Tables and plots of an evaluation: results.csv (one row per scene and preset),
results.md (the paper's layout: per preset, the mean of each metric over scenes, time
and peak memory; then the headline metric per scene), plots/ (per-scene bars, camera
trajectories against the ground truth, speed against quality)."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["write_csv", "write_markdown", "write_plots"]

_COST = ("time_s", "compile_s", "mem_gb", "status")


def _metrics(rows: Sequence[dict], preferred: Sequence[str]) -> list[str]:
    present = {k for r in rows for k in r if k not in ("scene", "preset", "frames", *_COST)}
    return [m for m in preferred if m in present]


def _mean(vals) -> float:
    v = [x for x in vals if x is not None and isinstance(x, (int, float)) and math.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def _fmt(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.4f}" if abs(x) < 100 else f"{x:.1f}"


def write_csv(path: Path, rows: Sequence[dict]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in keys})


def write_markdown(path: Path, rows: Sequence[dict], metrics: Sequence[str], title: str,
                   higher: Sequence[str] = ()) -> None:
    """Summary table (rows = presets; columns = mean over scenes of each metric, mean and
    total time, mean and max peak memory) and a per-scene table of the first metric."""
    metrics = _metrics(rows, metrics)
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    arrow = {m: " ↑" if m in higher else " ↓" for m in metrics}
    lines = [f"# {title}", "", f"{len(scenes)} scene(s); metrics are means over scenes. Time: model run per scene "
             "(without compilation); memory: XLA peak of the compiled program.", ""]
    head = ["preset", *(m + arrow[m] for m in metrics), "time/scene (s)", "total time (s)", "mem mean (GB)",
            "mem max (GB)"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in presets:
        rs = [r for r in rows if r["preset"] == p and r.get("status") != "OOM"]
        if not rs:  # every scene ran out of memory: the paper's "OOM" row
            lines.append("| " + " | ".join([p, *["OOM"] * (len(head) - 1)]) + " |")
            continue
        mem = [r.get("mem_gb") for r in rs if r.get("mem_gb") is not None]
        cells = [p, *(_fmt(_mean(r.get(m) for r in rs)) for m in metrics), _fmt(_mean(r["time_s"] for r in rs)),
                 _fmt(sum(r["time_s"] for r in rs)), _fmt(_mean(mem)), _fmt(max(mem) if mem else None)]
        n_oom = sum(r.get("status") == "OOM" for r in rows if r["preset"] == p)
        lines.append("| " + " | ".join(cells) + " |" + (f" ({n_oom} scene(s) OOM, not in the means)" if n_oom else ""))
    if metrics:
        m = metrics[0]
        lines += ["", f"## {m} per scene", "", "| preset | " + " | ".join(scenes) + " | mean |",
                  "|" + "---|" * (len(scenes) + 2)]
        for p in presets:
            by = {r["scene"]: "OOM" if r.get("status") == "OOM" else r.get(m) for r in rows if r["preset"] == p}
            vals = [v for v in by.values() if v != "OOM"]
            lines.append("| " + " | ".join([p, *("OOM" if by.get(s) == "OOM" else _fmt(by.get(s)) for s in scenes),
                                            _fmt(_mean(vals))]) + " |")
    path.write_text("\n".join(lines) + "\n")


def _centers(w2c: np.ndarray) -> np.ndarray:
    return -np.einsum("sji,sj->si", w2c[:, :3, :3], w2c[:, :3, 3])


def write_plots(folder: Path, rows: Sequence[dict], metrics: Sequence[str], runs: Path, reference: str | None) -> list[Path]:
    """per_scene.png, speed_quality.png and trajectory_<scene>.png (top view, x-z, of
    the reference cameras and each preset's, Sim(3)-aligned on camera centres)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rvggt_jax.eval.alignment import apply_sim3, umeyama

    folder.mkdir(parents=True, exist_ok=True)
    rows = [r for r in rows if r.get("status") != "OOM"]
    metrics = _metrics(rows, metrics)
    if not metrics:
        return []
    m = metrics[0]
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    written = []

    fig, ax = plt.subplots(figsize=(max(5, 1 + 0.8 * len(scenes) * len(presets)), 3.5))
    width = 0.8 / max(len(presets), 1)
    for j, p in enumerate(presets):
        by = {r["scene"]: r.get(m) for r in rows if r["preset"] == p}
        ax.bar(np.arange(len(scenes)) + j * width, [by.get(s) if by.get(s) is not None else np.nan for s in scenes],
               width, label=p)
    ax.set_xticks(np.arange(len(scenes)) + width * (len(presets) - 1) / 2, scenes, rotation=30, ha="right", fontsize=7)
    ax.set_ylabel(m)
    ax.legend(fontsize=7)
    fig.tight_layout()
    written.append(folder / "per_scene.png")
    fig.savefig(written[-1], dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    for p in presets:
        rs = [r for r in rows if r["preset"] == p]
        x, y = _mean(r["time_s"] for r in rs), _mean(r.get(m) for r in rs)
        ax.scatter([x], [y])
        ax.annotate(p, (x, y), fontsize=8)
    ax.set_xlabel("time per scene (s)")
    ax.set_ylabel(m)
    fig.tight_layout()
    written.append(folder / "speed_quality.png")
    fig.savefig(written[-1], dpi=100)
    plt.close(fig)

    for s in scenes:
        fig, ax = plt.subplots(figsize=(4.5, 4))
        ref_drawn = False
        for p in presets:
            f = runs / p / f"{s.replace('/', '__')}.npz"
            if not f.exists():
                continue
            z = np.load(f)
            ref = z["ref_extrinsics"] if reference and "ref_extrinsics" in z else z.get("gt_extrinsics")
            if ref is None or ref.ndim != 3 or len(ref) < 3:
                continue
            c_ref, c_pred = _centers(ref), _centers(z["pred_extrinsics"])
            try:
                c_pred = apply_sim3(c_pred, *umeyama(c_pred, c_ref))
            except ValueError:
                pass
            if not ref_drawn:
                ax.plot(c_ref[:, 0], c_ref[:, 2], "--", color="gray", marker="o", ms=3,
                        label=reference or "ground truth")
                ref_drawn = True
            ax.plot(c_pred[:, 0], c_pred[:, 2], marker=".", label=p)
        if not ref_drawn:
            plt.close(fig)
            continue
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x")
        ax.set_ylabel("z")
        ax.set_title(f"{s}: camera centres (Sim(3)-aligned)", fontsize=8)
        ax.legend(fontsize=7)
        fig.tight_layout()
        written.append(folder / f"trajectory_{s.replace('/', '__')}.png")
        fig.savefig(written[-1], dpi=100)
        plt.close(fig)
    return written
