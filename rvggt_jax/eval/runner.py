"""Run compression presets over a dataset's scenes, score them, keep per-scene results
on disk so that an interrupted run resumes.

Layout of OUT:
    OUT/runs/<preset>/<scene>.json    metrics, time, memory, settings of one (scene, preset)
    OUT/runs/<preset>/<scene>.npz     predicted (+ ground-truth) extrinsics, for the plots
    OUT/results.csv, OUT/results.md, OUT/plots/*.png   (rvggt_jax.eval.report)

A result is reused when its settings (dataset, frames, weights, image size, ...) equal
the current run's; anything else is recomputed.

Long sequences (KITTI, TUM: `Protocol.sequence`) run in one forward like any scene, up
to `MAX_ONE_FORWARD_FRAMES` frames; with `chunk_frames` set, the predictor gets the
scene's image paths instead of network images and predicts them in overlapping chunks
(the command line wires in `rvggt_jax.app.long_sequence.predict_sequence`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from rvggt_jax.eval.datasets import load_scenes, sample_indices
from rvggt_jax.eval.network_inputs import network_images
from rvggt_jax.eval.protocols import PROTOCOLS, against_reference

__all__ = ["EvalSettings", "MAX_ONE_FORWARD_FRAMES", "Predictor", "evaluate"]

MAX_ONE_FORWARD_FRAMES = 1000
"""The most frames of a sequence dataset scored in one forward (ScanNet-50's largest
protocol runs 1000): longer sequences need chunks, or fewer frames."""


@dataclasses.dataclass(frozen=True)
class EvalSettings:
    """One evaluation run. frames / stride / sampling / seed: frame selection (None =
    the protocol's default); against: None (score against ground truth) or a preset
    name whose outputs are the reference; size: network image width. chunk_frames /
    overlap / loop_closure: predict a sequence dataset's scenes in chunks of that many
    frames sharing `overlap` (None: one forward)."""

    dataset: str
    root: str
    presets: tuple[str, ...]
    out: str
    weights: str
    frames: int | None = None
    stride: int | None = None
    sampling: str | None = None
    seed: int = 0
    scenes: tuple[str, ...] | None = None
    size: int = 518
    against: str | None = None
    gt_root: str | None = None
    chunk_frames: int | None = None
    overlap: int | None = None
    loop_closure: bool = False

    def frame_selection(self) -> dict[str, Any]:
        p = PROTOCOLS.get(self.dataset)
        return dict(stride=self.stride or (p.stride if p and self.frames is None else 1),
                    frames=self.frames if self.frames is not None else (p.frames if p and self.stride is None else None),
                    how=self.sampling or (p.sampling if p else "first"), seed=self.seed)

    def key(self, preset: str) -> dict[str, Any]:
        """What a stored result must match to be reused."""
        key = dict(dataset=self.dataset, preset=preset, weights=str(self.weights), size=self.size,
                   against=self.against, **self.frame_selection())
        if self.chunk_frames is not None:  # only then: one-forward results stored before stay valid
            key.update(chunk_frames=self.chunk_frames, overlap=self.overlap, loop_closure=self.loop_closure)
        return key


def scene_indices(settings: EvalSettings, n: int) -> list[int]:
    """The frames (indices into a scene of n frames) this run evaluates."""
    sel = settings.frame_selection()
    stride = sel["stride"]
    proto = PROTOCOLS.get(settings.dataset)
    if proto is not None and proto.stride_cap_half:
        stride = max(1, min(stride, n // 2))
    return sample_indices(n, stride=stride, frames=sel["frames"], how=sel["how"], seed=sel["seed"])


def _inputs(settings: EvalSettings, scene) -> tuple[Any, Any]:
    """What the predictor is given for the frames of `scene`: (network images [S, 3, H,
    W], their `ImageInfo`s), or, for a chunked run, (the image paths, None): chunks are
    loaded one at a time, never the whole sequence."""
    if settings.chunk_frames is not None:
        return list(scene.image_paths), None
    proto = PROTOCOLS.get(settings.dataset)
    if proto is not None and proto.sequence and len(scene) > MAX_ONE_FORWARD_FRAMES:
        raise ValueError(f"{settings.dataset} sequence {scene.name} has {len(scene)} frames, more than one forward "
                         f"takes here ({MAX_ONE_FORWARD_FRAMES}): add --chunk-frames C --overlap O (e.g. "
                         "--chunk-frames 60 --overlap 15), or select fewer frames with --stride / --frames")
    return network_images(scene.image_paths, settings.size)


def _slug(name: str) -> str:
    return name.replace("/", "__").replace("\\", "__") or "scene"


class Predictor:
    """The model under every preset: compiled once per (preset, input shape), timed
    without the compilation; peak memory from XLA's buffer assignment of the compiled
    program (arguments + outputs + temporaries)."""

    def __init__(self, weights: str):
        import rvggt_jax

        self.params, self.config = rvggt_jax.load_pretrained(weights, skip_track=True)
        self._compiled: dict = {}

    def __call__(self, preset: str, images: np.ndarray, **_) -> tuple[dict, dict]:
        """outputs of `preset` on images [S, 3, H, W] as numpy (extrinsics [S, 3, 4],
        intrinsics [S, 3, 3], depth [S, H, W], depth_conf, world_points [S, H, W, 3],
        world_points_conf) and the cost {"time_s", "compile_s", "mem_gb"}."""
        import jax

        from rvggt_jax import rvggt_forward
        from rvggt_jax.geometry import pose_encoding_to_extri_intri

        cfg = self.config.with_compression(preset)
        key = (preset, images.shape)
        t0 = time.perf_counter()
        if key not in self._compiled:
            self._compiled[key] = jax.jit(rvggt_forward).lower(self.params, images, cfg).compile()
        compiled = self._compiled[key]
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(self.params, images, cfg))
        run_s = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        peak = None if mem is None else (mem.argument_size_in_bytes + mem.output_size_in_bytes
                                         + mem.temp_size_in_bytes - mem.alias_size_in_bytes)
        h, w = images.shape[-2:]
        e, k = pose_encoding_to_extri_intri(out["pose_enc"], (h, w))
        pred = dict(extrinsics=np.asarray(e, np.float64)[0], intrinsics=np.asarray(k, np.float64)[0],
                    depth=np.asarray(out["depth"])[0, ..., 0], depth_conf=np.asarray(out["depth_conf"])[0])
        if "world_points" in out:
            pred["world_points"] = np.asarray(out["world_points"])[0]
            pred["world_points_conf"] = np.asarray(out["world_points_conf"])[0]
        return pred, dict(time_s=run_s, compile_s=compile_s, mem_gb=None if peak is None else peak / 2**30)


def _load(path: Path, key: dict) -> dict | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if doc.get("settings") == key else None


def _save(path: Path, doc: dict, arrays: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path.with_suffix(".npz"), **{k: v for k, v in arrays.items() if v is not None})
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=1, default=float))
    tmp.replace(path)  # a result on disk is always whole: resuming never reads half a file


def is_out_of_memory(e: BaseException) -> bool:
    """Whether an exception from running the model means it ran out of memory."""
    msg = str(e)
    return isinstance(e, MemoryError) or "RESOURCE_EXHAUSTED" in msg or "out of memory" in msg.lower()


def evaluate(settings: EvalSettings, progress: bool = True, say: Callable[[str], None] = print,
             predictor_factory: Callable[[str], Any] = Predictor) -> list[dict]:
    """Run every preset on every scene (skipping stored results); returns one row per
    (scene, preset): {"scene", "preset", "frames", metrics..., "time_s", "compile_s",
    "mem_gb"}, or {"scene", "preset", "frames", "status": "OOM"} where the model ran out
    of memory (as the paper's tables mark it; kept on disk: delete the run's json to
    retry). `predictor_factory(weights)` -> callable(preset, images, scene=...) ->
    (outputs, cost), `Predictor` unless testing; with `settings.chunk_frames`, `images`
    is the scene's list of image paths and the outputs need only "extrinsics" [S, 3, 4].
    Raises DatasetError / ValueError for bad input."""
    from tqdm.auto import tqdm

    opts = {"gt_root": Path(settings.gt_root)} if settings.gt_root else {}
    scenes = load_scenes(settings.dataset, settings.root, settings.scenes, **opts)
    if settings.against is None and settings.dataset not in PROTOCOLS:
        raise ValueError(f"dataset {settings.dataset!r} has no ground truth: use --against dense")
    if settings.against is None and any(s.extrinsics is None for s in scenes):
        raise ValueError("these scenes have no cameras: use --against dense")
    if settings.chunk_frames is not None and (settings.against or not PROTOCOLS[settings.dataset].sequence):
        raise ValueError("chunked prediction is for sequence datasets scored against their ground truth")
    runs = Path(settings.out) / "runs"
    predictor = None
    rows: list[dict] = []
    presets = list(settings.presets)
    if settings.against and settings.against in presets:
        presets.remove(settings.against)  # the reference is not compared with itself
    for scene in tqdm(scenes, desc="scenes", unit="scene", disable=not progress):
        sub = scene.subset(scene_indices(settings, len(scene)))
        todo = []
        for preset in presets:
            path = runs / preset / f"{_slug(scene.name)}.json"
            doc = _load(path, settings.key(preset))
            if doc is None:
                todo.append((preset, path))
            else:
                rows.append(doc["row"])
        if not todo:
            continue
        images, infos = _inputs(settings, sub)  # first: a too-long sequence fails before the model loads
        if predictor is None:
            predictor = predictor_factory(settings.weights)
        ref_pred = None
        if settings.against:
            try:
                ref_pred, _ = predictor(settings.against, images, scene=sub)
            except Exception as e:
                if not is_out_of_memory(e):
                    raise
                say(f"warning: {scene.name}: the reference {settings.against} ran out of memory; scene skipped")
                continue
        for preset, path in tqdm(todo, desc=f"presets ({scene.name})", unit="preset", leave=False,
                                 disable=not progress):
            base = dict(scene=scene.name, preset=preset, frames=len(sub))
            try:
                pred, cost = predictor(preset, images, scene=sub)
            except Exception as e:
                if not is_out_of_memory(e):
                    raise
                say(f"warning: {scene.name} / {preset}: out of memory")
                row = dict(base, status="OOM")
                rows.append(row)
                _save(path, dict(settings=settings.key(preset), row=row), {})
                continue
            if ref_pred is not None:
                metrics = against_reference(pred, ref_pred)
            else:
                metrics = PROTOCOLS[settings.dataset].score(sub, pred, infos)
            row = dict(base, **metrics, **cost)
            rows.append(row)
            _save(path, dict(settings=settings.key(preset), row=row),
                  dict(pred_extrinsics=pred["extrinsics"], gt_extrinsics=sub.extrinsics,
                       ref_extrinsics=None if ref_pred is None else ref_pred["extrinsics"]))
            bad = [k for k, v in metrics.items() if isinstance(v, float) and not math.isfinite(v)]
            if bad:
                say(f"warning: {scene.name} / {preset}: non-finite {', '.join(bad)}")
    return rows
