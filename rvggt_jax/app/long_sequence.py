"""`rvggt reconstruct SRC --chunk-frames C --overlap O [--loop-closure]`: sequences longer
than one forward holds.

The frames (a video, or a folder sorted by name) are cut into chunks of C frames sharing
O frames with the next (`rvggt_jax.sequence.plan_chunks`); each chunk is one forward with
the run's preset, dtype and devices, compiled once (every chunk has the same shape); its
prediction goes to OUT/chunks/ on disk (`ChunkStore`) and leaves memory. Then the chunks
are chained by Sim(3) on their shared frames, loops closed on request
(`rvggt_jax.sequence.align_chunks`), and the outputs written chunk by chunk
(`rvggt_jax.app.long_export`). Host memory is O(C), not O(S); a stopped run resumes from
its last finished chunk (OUT/chunks/run.json records what the cache was made with).
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from rvggt_jax.app.console import say, warn
from rvggt_jax.app.messages import CLIError, one_line
from rvggt_jax.app.options import ReconstructOptions

__all__ = ["CHUNKS_DIR", "ChunkedRun", "check_frame_order", "predict_sequence", "reconstruct_chunked", "resumable"]

CHUNKS_DIR = "chunks"
RUN_FILE = "run.json"
AUTO = "auto"
_AUTO_PROBES = (8, 16)  # frame counts whose memory plans give the line that picks C


def check_frame_order(paths: Sequence[Path]) -> None:
    """`CLIError` unless the names of `paths` (sorted by name) carry frame numbers in that
    same order: chunks are aligned on the frames they share, so chunking assumes that
    consecutive files are consecutive views. Sizes may differ."""
    keys = []
    for p in paths:
        numbers = tuple(int(x) for x in re.findall(r"\d+", Path(p).stem))
        if not numbers:
            raise CLIError(f"--chunk-frames needs the frames in capture order, and {Path(p).name!r} has no frame "
                           f"number in its name: name the files in order (frame_0001.jpg, frame_0002.jpg, ...) "
                           f"or pass a video (the order matters: chunks are aligned on the frames they share)")
        keys.append(numbers)
    for (a, ka), (b, kb) in zip(zip(paths, keys), zip(paths[1:], keys[1:])):
        if kb < ka:
            raise CLIError(f"--chunk-frames needs the frames in capture order: {Path(a).name!r} sorts before "
                           f"{Path(b).name!r} by name but has the larger frame number; zero-pad the numbers "
                           f"(frame_0002.jpg) so that name order is capture order (the order matters: chunks are "
                           f"aligned on the frames they share)")


def resumable(out_dir: Path) -> bool:
    """Whether `out_dir` holds an unfinished or finished chunked run (its cache's run.json)."""
    return (Path(out_dir) / CHUNKS_DIR / RUN_FILE).is_file()


@dataclasses.dataclass
class ChunkedRun:
    """One long run: the frames, their network size, the model, and the chunk cache.

    paths [S] the image files in order; hw the network input (H, W) of every chunk;
    chunk_frames / overlap as resolved (C may have been "auto")."""

    paths: list[Path]
    hw: tuple[int, int]
    params: dict
    config: object
    options: ReconstructOptions
    chunk_frames: int
    overlap: int
    compiled: object = None
    mesh: object = None
    weights_name: str = "the checkpoint"

    # ---- one forward ------------------------------------------------------------------

    def predict(self, frames: Sequence[int]):
        """(ChunkPrediction, depth [F, H, W], valid [F, H, W], infos) of one forward on
        `frames` (sequence indices), in the frame of the first one's camera. A list
        shorter than the compiled chunk is topped up with neighbouring frames (one
        program for every call: `verify` of loop closure too) and cut back after."""
        from rvggt_jax.app.model_runner import run_model
        from rvggt_jax.app.pipeline import apply_masks, sanitize_cameras
        from rvggt_jax.geometry import pose_encoding_to_extri_intri
        from rvggt_jax.io.images import network_images
        from rvggt_jax.sequence import ChunkPrediction

        frames = [int(f) for f in frames]
        run = _top_up(frames, self.chunk_frames, len(self.paths))
        images, infos = self._load(run)
        valid = np.stack([info.valid_mask(*self.hw) for info in infos])
        if self.options.masks is not None:
            masks = self._masks(run, infos)
            images, valid = apply_masks(images, masks), valid & masks
        compiled = self.compiled if len(run) == self.chunk_frames else None
        out = run_model(self.params, network_images(images), self.config, self.weights_name,
                        compiled=compiled, mesh=self.mesh if compiled is not None else None)
        ext, intr = (np.asarray(a)[0] for a in pose_encoding_to_extri_intri(out["pose_enc"][None], self.hw))
        ext, intr, repairs = sanitize_cameras(ext, intr, self.hw)
        for msg in repairs:
            warn(f"frames {run[0]}..{run[-1]}: {msg}")
        n = len(frames)
        depth = np.asarray(out["depth"], np.float32)[:n, ..., 0]
        conf_key = "world_points_conf" if self.options.points_from == "pointmap" else "depth_conf"
        conf = np.asarray(out[conf_key], np.float32)[:n]
        if self.options.points_from == "pointmap":
            points = np.asarray(out["world_points"], np.float32)[:n].copy()
            points[~valid[:n]] = np.nan
        else:
            from rvggt_jax.sequence.store import DepthPoints

            points = DepthPoints(depth, ext[:n], intr[:n], valid[:n])
        desc = out.get("descriptors")
        pred = ChunkPrediction(frames=np.asarray(frames), extrinsics=ext[:n], intrinsics=intr[:n], points=points,
                               confidence=np.where(valid[:n], conf, 0.0).astype(np.float32),
                               descriptors=None if desc is None else np.asarray(desc)[:n])
        return pred, depth, valid[:n], infos[:n]

    def _load(self, frames: list[int]):
        from rvggt_jax.io.images import TARGET_SIZE, ImageLoadError, load_images_with_info

        try:
            images, infos = load_images_with_info([self.paths[f] for f in frames], mode=self.options.mode,
                                                  exif_orientation=self.options.exif_orientation, pad_to=self.hw,
                                                  target=self.options.size or TARGET_SIZE)
        except ImageLoadError as e:
            raise CLIError(str(e)) from None
        if images.shape[2:] != tuple(self.hw):
            raise CLIError(f"frames {frames[0]}..{frames[-1]} come out at {images.shape[3]}x{images.shape[2]}, "
                           f"the sequence at {self.hw[1]}x{self.hw[0]}: an image changed since the run started")
        return images, infos

    def _masks(self, frames: list[int], infos):
        from rvggt_jax.io.masks import MaskError, find_masks, load_masks

        try:
            paths = find_masks([self.paths[f] for f in frames], self.options.masks)
            return load_masks(paths, infos, self.hw, self.options.mode, exif_orientation=self.options.exif_orientation)
        except MaskError as e:
            raise CLIError(f"--masks: {e}") from None

    # ---- the chunks -------------------------------------------------------------------

    def fingerprint(self) -> dict:
        """What a cached chunk depends on: a rerun with the same fingerprint resumes."""
        o = self.options
        return dict(frames=[p.name for p in self.paths], sizes=[p.stat().st_size for p in self.paths],
                    network_hw=list(self.hw), chunk_frames=self.chunk_frames, overlap=self.overlap,
                    preset=o.preset, dtype=o.dtype, mode=o.mode, points_from=o.points_from,
                    exif_orientation=o.exif_orientation, masks=None if o.masks is None else str(o.masks),
                    loop_closure=o.loop_closure, compression=str(getattr(self.config, "compression", "")))

    def run_chunks(self, store, manifest, quiet: bool) -> list[np.ndarray]:
        """Predict every chunk not yet in `store` (a progress bar per chunk), writing the
        manifest after each so that a killed run's cache is listed too. Returns the plan."""
        from tqdm.auto import tqdm

        from rvggt_jax.sequence import plan_chunks

        plan = plan_chunks(len(self.paths), self.chunk_frames, self.overlap)
        todo = [k for k in range(len(plan)) if not store.done(k)]
        if len(todo) < len(plan):
            say(quiet, f"resuming: {len(plan) - len(todo)} of {len(plan)} chunks already done in {store.folder}")
        with tqdm(total=len(plan), initial=len(plan) - len(todo), desc="chunks", unit="chunk", disable=quiet,
                  leave=False) as bar:
            for k in todo:
                pred, depth, valid, infos = self.predict(plan[k])
                meta = dict(infos=[dataclasses.asdict(i) for i in infos])
                extra = {}
                if self.options.points_from == "pointmap":
                    extra["world_points"] = np.asarray(pred.points, np.float32)
                store.save(k, pred, depth=depth, valid=valid, meta=meta, **extra)
                manifest.write()
                bar.update(1)
        return plan


def _top_up(frames: list[int], size: int, total: int) -> list[int]:
    """`frames` followed by the nearest other frames of the sequence, up to `size` frames
    (or all `total`): a forward of the compiled size that still starts at frames[0]."""
    if len(frames) >= size:
        return frames
    chosen, seen = list(frames), set(frames)
    for step in range(1, total):
        for f in frames:
            for g in (f - step, f + step):
                if 0 <= g < total and g not in seen and len(chosen) < size:
                    chosen.append(g)
                    seen.add(g)
        if len(chosen) >= min(size, total):
            break
    return chosen


def resolve_chunk_frames(value, config, hw, options: ReconstructOptions, frames: int) -> int:
    """C of `--chunk-frames`: a number as given, or "auto": the largest chunk XLA's memory
    plan fits on this device (a line through the plans of two small chunks, then
    checked), at most the whole sequence."""
    if value != AUTO:
        return int(value)
    from rvggt_jax.planning.memory import device_memory_bytes, memory_report

    have, what = device_memory_bytes()
    if have is None:
        raise CLIError("--chunk-frames auto needs to know the device's memory; set RVGGT_MEMORY_LIMIT_GB or give a "
                       "number (e.g. --chunk-frames 60)")
    sizes = [memory_report(config, n, *hw, param_dtype=options.dtype, image_dtype="uint8").total_bytes
             for n in _AUTO_PROBES]
    per_frame = max((sizes[1] - sizes[0]) / (_AUTO_PROBES[1] - _AUTO_PROBES[0]), 1.0)
    fit = int((0.9 * have - (sizes[0] - per_frame * _AUTO_PROBES[0])) / per_frame)
    chunk = max(2, min(fit, frames))
    if fit < 2:
        raise CLIError(f"--chunk-frames auto: not even 2 frames of {hw[1]}x{hw[0]} fit {what} "
                       f"({have / 1e9:.1f} GB); try --preset regime or --dtype bfloat16")
    return chunk


def predict_sequence(image_paths: Sequence[Path], params, config, *, chunk_frames: int, overlap: int,
                     loop_closure: bool = False, mode: str = "crop", cache_dir: Path | None = None,
                     quiet: bool = True, conf_threshold: str = "50%", size: int = 518):
    """The `rvggt_jax.sequence.Trajectory` of the images `image_paths` (in order) predicted
    chunk by chunk by the model (`params`, `config`) and aligned, for the evaluation of
    long sequences. Chunks go to `cache_dir` (default: a temporary folder)."""
    import tempfile

    from rvggt_jax.app.outdir import Manifest
    from rvggt_jax.io.images import network_shape
    from rvggt_jax.sequence import ChunkStore

    paths = [Path(p) for p in image_paths]
    options = ReconstructOptions(mode=mode, size=size, chunk_frames=chunk_frames, overlap=overlap,
                                 loop_closure=loop_closure, quiet=quiet, conf_threshold=conf_threshold)
    hw, _ = network_shape(paths, mode, target=size)
    if loop_closure:
        config = config.with_outputs(descriptors=True)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(cache_dir) if cache_dir is not None else Path(tmp)
        run = ChunkedRun(paths, hw, params, config, options, min(chunk_frames, len(paths)), overlap)
        store = ChunkStore(folder / CHUNKS_DIR)
        run.run_chunks(store, Manifest(folder), quiet)
        return align(run, store)


def align(run: ChunkedRun, store):
    """The chunks of `store` chained (and loops closed) into a `Trajectory`; an overlap
    that cannot be aligned is a `CLIError` naming the options that help. The points
    aligned on are those --conf-threshold keeps: "P%" the chunks' P-th percentile of the
    shared frames' confidences, a number that absolute confidence."""
    from rvggt_jax.app.pipeline import parse_threshold
    from rvggt_jax.errors import InputError
    from rvggt_jax.sequence import AlignOptions, align_chunks, plan_chunks

    plan = plan_chunks(len(run.paths), run.chunk_frames, min(run.overlap, run.chunk_frames - 1))
    chunks = [store.load(k, points_from=run.options.points_from) for k in range(len(plan))]
    thr = parse_threshold(run.options.conf_threshold)
    options = (AlignOptions(conf_quantile=min(thr[0], 99.0) / 100.0) if isinstance(thr, tuple)
               else AlignOptions(conf_threshold=float(thr), conf_quantile=0.0))

    def verify(frames: list[int]):
        return run.predict(frames)[0]

    try:
        return align_chunks(chunks, loop_closure=run.options.loop_closure,
                            verify=verify if run.options.loop_closure else None, options=options)
    except InputError as e:  # AlignmentError too: it names the chunks, --overlap and --conf-threshold
        raise CLIError(f"cannot chain the chunks: {one_line(e)}") from None


def write_run_file(store_folder: Path, fingerprint: dict) -> None:
    store_folder.mkdir(parents=True, exist_ok=True)
    (store_folder / RUN_FILE).write_text(json.dumps(fingerprint, indent=1) + "\n")


def check_run_file(store_folder: Path, fingerprint: dict) -> None:
    """`CLIError` when the cache in `store_folder` was made with other settings than
    `fingerprint` (then resuming would mix two runs)."""
    try:
        cached = json.loads((store_folder / RUN_FILE).read_text())
    except (OSError, ValueError):
        return
    diff = [k for k in fingerprint if cached.get(k) != fingerprint[k]]
    if diff:
        shown = ", ".join(f"{k} {cached.get(k)!r} -> {fingerprint[k]!r}" for k in diff if k not in ("frames", "sizes"))
        if {"frames", "sizes"} & set(diff):
            shown = (shown + ", " if shown else "") + "the input frames changed"
        raise CLIError(f"{store_folder.parent} holds a chunked run made with other settings ({shown}); pass "
                       f"--overwrite to start over, or choose another folder")


def reconstruct_chunked(chosen: list[Path], source: Path, weights, local_weights, out_dir: Path,
                        options: ReconstructOptions, manifest) -> dict:
    """`reconstruct_folder` with --chunk-frames: the frames `chosen` (in order) predicted
    chunk by chunk into OUT/chunks/ (resuming a stopped run), aligned, and written."""
    import time

    from rvggt_jax.app.model_runner import check_memory, model_for
    from rvggt_jax.app.long_export import export_chunked
    from rvggt_jax.io.images import ImageLoadError, network_shape
    from rvggt_jax.sequence import ChunkStore, plan_chunks

    t0 = time.perf_counter()
    try:
        hw, bad = network_shape(chosen, options.mode, exif_orientation=options.exif_orientation,
                                on_error="skip" if options.skip_bad else "raise", target=options.size or 518)
    except ImageLoadError as e:
        raise CLIError(f"{e} (--skip-bad leaves unreadable images out)") from None
    for p in bad:
        warn(f"--skip-bad: skipped unreadable image {p}")
    chosen = [p for p in chosen if str(p) not in set(bad)]
    if options.shared_camera:  # from the headers, before any chunk runs
        import types

        from rvggt_jax.app.options import check_one_size
        from rvggt_jax.io.images import upright_size

        check_one_size([types.SimpleNamespace(name=p.name, width=w, height=h) for p in chosen
                        for w, h in [upright_size(p, options.exif_orientation)]])
    if len(chosen) < 2:
        raise CLIError(f"--chunk-frames needs at least 2 frames; got {len(chosen)}")
    params, config = model_for(local_weights, weights, options)
    if options.loop_closure:
        config = config.with_outputs(descriptors=True)
    chunk = min(resolve_chunk_frames(options.chunk_frames, config, hw, options, len(chosen)), len(chosen))
    overlap = options.overlap if options.overlap is not None else max(1, chunk // 4)
    if overlap >= chunk and chunk < len(chosen):
        raise CLIError(f"--overlap {overlap} must be smaller than the chunk ({chunk} frames); e.g. --overlap "
                       f"{max(1, chunk // 4)}")
    report, mesh = check_memory(config, (chunk, *hw), options, "uint8")
    run = ChunkedRun(list(chosen), hw, params, config, options, chunk, overlap, compiled=report.compiled,
                     mesh=mesh, weights_name=str(weights))
    store = ChunkStore(out_dir / CHUNKS_DIR)
    check_run_file(store.folder, run.fingerprint())
    write_run_file(store.folder, run.fingerprint())
    plan = plan_chunks(len(chosen), chunk, min(overlap, chunk - 1))
    say(options.quiet, f"{len(chosen)} frames of {hw[1]}x{hw[0]} in {len(plan)} chunk{'s' * (len(plan) != 1)} of "
                       f"{chunk} (overlap {overlap}{', loop closure' if options.loop_closure else ''})")
    run.run_chunks(store, manifest, options.quiet)
    trajectory = align(run, store)
    if trajectory.loops:
        say(options.quiet, f"loop closure: {len(trajectory.loops)} loop(s) verified and closed")
    elif options.loop_closure:
        say(options.quiet, "loop closure: no loop found")
    summary = export_chunked(out_dir, run, store, trajectory, source, weights)
    summary["seconds"] = time.perf_counter() - t0
    summary["chunks"] = len(plan)
    return summary
