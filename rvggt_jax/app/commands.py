"""What `rvggt reconstruct` and `rvggt demo` do: inputs (a folder of images or a video)
-> the model (`rvggt_jax.app.pipeline`) -> every output file (`rvggt_jax.io.export`).

Order matters for the user: everything that can be checked cheaply (options, the input,
the output folder being writable and not holding another run) is checked before the
weights are loaded or downloaded and long before inference. Failures raise `CLIError`
(one line, see `rvggt_jax.app.messages`); warnings go to stderr as `rvggt: warning: ...`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Sequence

from rvggt_jax.app.messages import CLIError, one_line

PROG = "rvggt"
DEFAULT_CONF_THRESHOLD = "50%"
EXAMPLES_DIR = Path(__file__).resolve().parents[1] / "examples_data"  # rvggt_jax/examples_data
DEMO_IMAGES = EXAMPLES_DIR / "images"
DEMO_WEIGHTS = EXAMPLES_DIR / "tiny"
FRAMES_DIR = "frames"  # video frames written here (the images the COLMAP model refers to)

RANDOM_WEIGHTS_NOTICE = (
    "NOTE: the demo runs a tiny VGGT with RANDOM weights (rvggt_jax/examples_data/tiny): it exercises "
    "the whole pipeline, the reconstruction itself is meaningless. For real results run "
    "`rvggt reconstruct IMAGES --weights facebook/VGGT-1B --out OUT`."
)


# ---------------------------------------------------------------------------------------
# messages
# ---------------------------------------------------------------------------------------


def _write(text: str, file) -> None:
    """Print a line without tearing an active progress bar."""
    try:
        from tqdm.auto import tqdm

        tqdm.write(text, file=file)
        file.flush()
    except ImportError:  # pragma: no cover
        print(text, file=file, flush=True)


def say(quiet: bool, *parts: Any) -> None:
    if not quiet:
        _write(" ".join(map(str, parts)), sys.stdout)


def warn(msg: str) -> None:
    _write(f"{PROG}: warning: {one_line(msg, 1000)}", sys.stderr)


def known_presets() -> tuple[str, ...]:
    from rvggt_jax.compression.config import PRESETS

    return tuple(PRESETS)


def select_frames(paths: Sequence[Path], max_frames: int | None) -> list[Path]:
    """At most `max_frames` of `paths`, evenly spaced over the sorted list, first and
    last included (all of them when `max_frames` is None or large enough)."""
    paths = list(paths)
    if max_frames is None or len(paths) <= max_frames:
        return paths
    if max_frames == 1:
        return paths[:1]
    n = len(paths)
    idx = sorted({round(i * (n - 1) / (max_frames - 1)) for i in range(max_frames)})
    return [paths[i] for i in idx]


# ---------------------------------------------------------------------------------------
# options
# ---------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, kw_only=True)
class ReconstructOptions:
    """How `rvggt reconstruct` (and `rvggt demo`) run: the command line's options, with its
    defaults. The CLI builds one from the parsed arguments; `reconstruct_folder` checks it
    (`check`) before it looks at anything else.

    Inputs:
      mode: "crop" (width 518, height centre-cropped to <= 518) or "pad" (longest side
        518, white-padded to square).
      max_frames: use at most this many images (or video frames), evenly spaced; None: all.
      every / fps: a video's frames to keep, every N-th or F per second (at most one of
        them; neither: 1 per second). Refused for a folder of images.
      skip_bad: leave out images that cannot be read (a warning names each) instead of
        stopping at the first.
      exif_orientation: apply the EXIF orientation of photos (False: read them as stored,
        upstream's behaviour).
    Model:
      preset: compression preset of the global attention (`known_presets()`); None: the
        checkpoint's.
      dtype: the aggregator's compute dtype, "float32" or "bfloat16" (the heads stay float32).
      devices: split the frames over this many local devices; None: all of them when
        there are several.
    Outputs:
      conf_threshold: keep points whose confidence is >= this number, or, written "P%",
        at or above the P-th percentile of all confidences ("0%" keeps every point).
      points_from: the point cloud from the "depth" maps unprojected with the predicted
        cameras or from the "pointmap" head.
      max_points: cap on the points written to points.ply (a random subset); None: no cap.
      all_colmap_points: write every point of points.ply to sparse/points3D.txt (default:
        a random subset of at most 100000).
      overwrite: reuse a non-empty output folder, deleting the files the previous rvggt run
        there wrote (its manifest) and nothing else.
      quiet: no progress bars or messages (errors and warnings only).
    """

    mode: str = "crop"
    max_frames: int | None = None
    every: int | None = None
    fps: float | None = None
    skip_bad: bool = False
    exif_orientation: bool = True
    preset: str | None = None
    dtype: str = "float32"
    devices: int | None = None
    conf_threshold: str | float = DEFAULT_CONF_THRESHOLD
    points_from: str = "depth"
    max_points: int | None = 2_000_000
    all_colmap_points: bool = False
    overwrite: bool = False
    quiet: bool = False

    def check(self) -> None:
        """Raise `CLIError` (one line, naming the command-line option) for a value out of
        range, before any input is read."""
        import math

        from rvggt_jax.app.pipeline import parse_threshold

        if self.mode not in ("crop", "pad"):
            raise CLIError(f"unknown mode {self.mode!r}; use crop or pad")
        try:
            parse_threshold(self.conf_threshold)
        except ValueError as e:
            raise CLIError(str(e)) from None
        if self.max_frames is not None and self.max_frames < 1:
            raise CLIError(f"--max-frames must be at least 1; got {self.max_frames}")
        if self.preset is not None and self.preset not in known_presets():
            raise CLIError(f"unknown preset {self.preset!r}; known presets: {', '.join(known_presets())}")
        if self.dtype not in ("float32", "bfloat16"):
            raise CLIError(f"unknown dtype {self.dtype!r}; use float32 or bfloat16")
        if self.max_points is not None and self.max_points < 1:
            raise CLIError(f"--max-points must be at least 1; got {self.max_points}")
        if self.points_from not in ("depth", "pointmap"):
            raise CLIError(f"unknown point source {self.points_from!r}; use depth or pointmap")
        if self.every is not None and self.fps is not None:
            raise CLIError("give --every or --fps, not both")
        if self.every is not None and self.every < 1:
            raise CLIError(f"--every must be at least 1; got {self.every}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise CLIError(f"--fps must be a positive number; got {self.fps}")


# ---------------------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------------------


def load_model(weights: str | Path, quiet: bool = True, name: str | Path | None = None):
    """`(params, config)` of a checkpoint (local path or hub repo id), without the
    track head (unused here); `name` is how messages call it (default: `weights`).
    Warnings of the loader become `rvggt: warning:` lines."""
    from rvggt_jax.weights.hub import HubError, resolve_checkpoint

    name = weights if name is None else name
    try:
        local = resolve_checkpoint(weights, progress=not quiet, say=lambda m: say(quiet, m))
    except HubError as e:
        raise CLIError(str(e)) from None
    if not Path(local).exists():
        raise CLIError(f"checkpoint not found: {name}")
    try:
        from rvggt_jax.weights.checkpoint import load_checkpoint

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            loaded = load_checkpoint(str(local), skip_track=True, progress=not quiet)
        for w in caught:
            if issubclass(w.category, UserWarning):
                warn(str(w.message))
        return loaded
    except Exception as e:
        if type(e).__name__ == "CheckpointError":
            raise CLIError(f"checkpoint {name} does not fit the model: {e}") from None
        if type(e).__name__ == "CheckpointFileError":
            raise CLIError(str(e)) from None
        raise CLIError(f"cannot load checkpoint {name}: {one_line(e)}") from None


def enable_compilation_cache() -> str | None:
    """Keep compiled programs across runs (the first run of a shape compiles for a while).

    Directory: $RVGGT_CACHE_DIR, else $XDG_CACHE_HOME/rvggt-jax/xla (~/.cache/...);
    RVGGT_CACHE_DIR=off disables it; a cache directory already configured for JAX
    (JAX_COMPILATION_CACHE_DIR) is left alone. Returns the directory in use, if any."""
    import jax

    try:
        current = jax.config.jax_compilation_cache_dir
        if current:
            return current
        d = os.environ.get("RVGGT_CACHE_DIR")
        if d is None:
            base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
            d = os.path.join(base, "rvggt-jax", "xla")
        if d.strip().lower() in ("", "0", "off", "none", "false"):
            return None
        os.makedirs(d, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", d)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
        return d
    except Exception:  # an unwritable cache only costs time
        return None


def run_model(params, images, config, weights, compiled=None, mesh=None) -> dict:
    """`rvggt_jax.app.pipeline.run_model` with its failures as one-line `CLIError`s naming `weights`."""
    from rvggt_jax.model.forward import InputError
    from rvggt_jax.app.pipeline import run_model as forward

    enable_compilation_cache()
    try:
        return forward(params, images, config, compiled, mesh)
    except InputError as e:
        raise CLIError(f"checkpoint {weights} does not fit the model: {one_line(e)}") from None
    except ValueError as e:  # a head missing
        raise CLIError(f"checkpoint {weights}: {one_line(e)}") from None


def devices_mesh(devices: int | None):
    """The "frames" mesh of `devices` local devices (None: all, when there are several),
    or None for one device."""
    import jax

    from rvggt_jax.parallel.sharded import frames_mesh

    n = len(jax.local_devices()) if devices is None else devices
    try:
        mesh = frames_mesh(n)
    except ValueError as e:
        raise CLIError(f"--devices {n}: {e}") from None
    return None if n == 1 else mesh


# ---------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------


def _check_local_checkpoint(weights: Path) -> None:
    """Fail now, not after loading the images, on a checkpoint that cannot be read:
    missing, not a safetensors/Orbax checkpoint, or a truncated .safetensors (its
    header is read: cheap)."""
    from rvggt_jax.weights.checkpoint import SAFETENSORS_NAME, CheckpointFileError, safetensors_shapes

    if not weights.exists():
        raise CLIError(f"checkpoint not found: {weights}")
    st = weights if weights.is_file() else weights / SAFETENSORS_NAME
    if weights.is_file() and weights.suffix != ".safetensors":
        pt = " (PyTorch .pt files are not read: use the repo's model.safetensors)" if weights.suffix in (
            ".pt", ".pth", ".bin") else ""
        raise CLIError(f"checkpoint {weights} is not a .safetensors file or a checkpoint folder{pt}")
    if st.is_file():
        try:
            safetensors_shapes(st)
        except CheckpointFileError as e:
            raise CLIError(str(e)) from None


def _image_inputs(src: Path, options: ReconstructOptions) -> list[Path]:
    """The images of the folder `src` (sorted by name) that the run uses: at most
    `options.max_frames`, evenly spaced; non-image entries are skipped."""
    from rvggt_jax.io.images import IMAGE_EXTENSIONS, find_images

    max_frames, quiet = options.max_frames, options.quiet
    try:
        paths, skipped = find_images(src)
    except (FileNotFoundError, NotADirectoryError) as e:
        raise CLIError(str(e)) from None
    if not paths:
        if not skipped:
            raise CLIError(f"image folder is empty: {src}")
        raise CLIError(f"no images in {src} ({len(skipped)} other entries skipped; "
                       f"image files end in {', '.join(IMAGE_EXTENSIONS)})")
    if skipped:
        say(quiet, f"skipping {len(skipped)} non-image entr{'y' if len(skipped) == 1 else 'ies'} in {src}")
    chosen = select_frames(paths, max_frames)
    if len(chosen) < len(paths):
        say(quiet, f"using {len(chosen)} of {len(paths)} images (--max-frames {max_frames}, evenly spaced)")
    return chosen


def _video_inputs(src: Path, out_dir: Path, options: ReconstructOptions) -> list[Path]:
    """Decode the kept frames of `src` (`options.every` / `fps` / `max_frames`) and write
    them to OUT/frames/<timestamp name>.jpg (the images every output refers to). Returns
    their paths."""
    from rvggt_jax.io.video import DEFAULT_FPS, VideoError, video_frames

    every, fps, max_frames, quiet = options.every, options.fps, options.max_frames, options.quiet
    how = f"every {every} frames" if every else f"{fps or DEFAULT_FPS:g} frames per second"
    say(quiet, f"decoding {src.name} ({how}{f', at most {max_frames}' if max_frames else ''}) ...")
    t0 = time.perf_counter()
    try:
        frames = video_frames(src, every=every, fps=fps, max_frames=max_frames)
    except (VideoError, ValueError) as e:
        raise CLIError(str(e)) from None
    folder = out_dir / FRAMES_DIR
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for f in frames:
        p = folder / f"{f.name}.jpg"
        f.image.save(p, quality=95)
        paths.append(p)
    say(quiet, f"kept {len(paths)} frames ({frames[0].time:.2f} s to {frames[-1].time:.2f} s) in "
               f"{time.perf_counter() - t0:.1f} s -> {folder}")
    return paths


# ---------------------------------------------------------------------------------------
# reconstruct
# ---------------------------------------------------------------------------------------


def reconstruct_folder(source: str | Path, weights: str | Path, out_dir: str | Path,
                       options: ReconstructOptions = ReconstructOptions()) -> dict:
    """Reconstruct the images of a folder (sorted by name) or the frames of a video file
    `source` with the checkpoint `weights` (a local path or a hub repo id) and write every
    output to `out_dir`, as `options` say. Returns the export summary. Raises `CLIError`
    with a one-line message.

    Everything cheap is checked first (the options, the input, the checkpoint file, the
    output folder), then the hub checkpoint is resolved (downloaded / converted), and only
    then are the video frames decoded and the model run."""
    from rvggt_jax.app.outdir import Manifest

    source, out_dir = Path(source), Path(out_dir)
    options.check()
    video = _check_source(source, options)
    _check_weights(weights)
    chosen = None if video else _image_inputs(source, options)
    created = not out_dir.exists()
    _prepare_output(out_dir, options)
    manifest = Manifest(out_dir)
    try:
        # a hub repo id: download / convert now, before reading any input (a failure here
        # says what is missing without having made the user wait)
        local_weights = _resolve_weights(weights, options.quiet)
        if video:
            chosen = _video_inputs(source, out_dir, options)
        return _reconstruct(chosen, source, weights, local_weights, out_dir, options)
    finally:
        if not manifest.write() and created:  # also after a failure: the next --overwrite removes exactly these
            try:
                out_dir.rmdir()  # a run that failed before writing anything leaves no empty folder behind
            except OSError:
                pass


def _check_source(source: Path, options: ReconstructOptions) -> bool:
    """Whether `source` is a video; `CLIError` when it is neither a video nor a folder, or
    when video options are given for a folder."""
    from rvggt_jax.io.video import is_video

    video = is_video(source)
    if not source.exists():
        raise CLIError(f"input not found: {source} (a folder of images or a video file)")
    if source.is_file() and not video:
        raise CLIError(f"not a folder of images or a video file: {source} (videos end in .mp4, .mov, ...)")
    if not video and (options.every is not None or options.fps is not None):
        raise CLIError("--every / --fps choose frames of a video; the input is a folder of images")
    return video


def _check_weights(weights: str | Path) -> None:
    """A local checkpoint is checked now (`_check_local_checkpoint`); a hub repo id later,
    by `_resolve_weights`."""
    from rvggt_jax.weights.hub import is_repo_id

    if not is_repo_id(weights):
        _check_local_checkpoint(Path(weights))


def _prepare_output(out_dir: Path, options: ReconstructOptions) -> None:
    from rvggt_jax.app.outdir import OutputDirError, prepare_output

    try:
        removed = prepare_output(out_dir, options.overwrite)
    except OutputDirError as e:
        raise CLIError(str(e)) from None
    if removed:
        say(options.quiet, f"--overwrite: removed {removed} files of the previous run in {out_dir}")


def _resolve_weights(weights: str | Path, quiet: bool) -> Path:
    """The local checkpoint of `weights` (a hub repo id downloaded and converted once)."""
    from rvggt_jax.weights.hub import HubError, resolve_checkpoint

    try:
        return resolve_checkpoint(weights, progress=not quiet, say=lambda m: say(quiet, m))
    except HubError as e:
        raise CLIError(str(e)) from None


_STAGES = ("loading weights", "checking memory", "running the model", "decoding cameras", "writing outputs")


def _reconstruct(chosen, source: Path, weights, local_weights, out_dir: Path, options: ReconstructOptions) -> dict:
    """`reconstruct_folder` once the inputs are chosen and the output folder is ready:
    load the images, then the model, check the memory, run, decode, write."""
    images, infos, chosen = _load_inputs(chosen, options)
    s, _, h, w = images.shape
    t0 = time.perf_counter()
    with _stage_bar(_STAGES, options.quiet) as stage:
        stage(0)
        params, config = _model_for(local_weights, weights, options)
        stage(1)
        report, mesh = _check_memory(config, (s, h, w), options)
        stage(2)
        out = run_model(params, images, config, weights, compiled=report.compiled, mesh=mesh)
        stage(3)
        recon = _decode(out, images, chosen, infos, options)
        stage(4)
        summary = _export(out_dir, recon, source, weights, config, options)
        stage(len(_STAGES))
    summary["seconds"] = time.perf_counter() - t0
    _tell_summary(summary, out_dir, options)
    return summary


def _load_inputs(chosen: list[Path], options: ReconstructOptions):
    """`(images, infos, chosen)`: the network inputs of `chosen` (a progress bar), the
    unreadable ones left out with a warning each under `skip_bad`."""
    from tqdm.auto import tqdm

    from rvggt_jax.io.images import ImageLoadError, load_images_with_info

    with tqdm(total=len(chosen), desc="loading images", unit="img", disable=options.quiet, leave=False) as bar:
        def progress(it):
            for x in it:
                yield x
                bar.update(1)

        try:
            images, infos = load_images_with_info(chosen, mode=options.mode, progress=progress,
                                                  exif_orientation=options.exif_orientation,
                                                  on_error="skip" if options.skip_bad else "raise")
        except ImageLoadError as e:
            bar.close()
            hint = "" if options.skip_bad else " (--skip-bad leaves unreadable images out)"
            raise CLIError(f"{e}{hint}") from None
    if options.skip_bad:
        loaded = {i.path for i in infos}
        for p in chosen:
            if os.fspath(p) not in loaded:
                warn(f"--skip-bad: skipped unreadable image {p}")
        chosen = [p for p in chosen if os.fspath(p) in loaded]
    s, _, h, w = images.shape
    say(options.quiet, f"loaded {s} image{'s' * (s != 1)} -> network input {w}x{h} ({options.mode})")
    return images, infos, chosen


@contextlib.contextmanager
def _stage_bar(stages: Sequence[str], quiet: bool):
    """A progress bar over `stages`, yielding `stage(i)`: stage i begins (the bar names it
    and counts the ones before it done); `stage(len(stages))`: the last one is done."""
    from tqdm.auto import tqdm

    with tqdm(total=len(stages), unit="step", disable=quiet, leave=False, desc=f"reconstruct ({stages[0]})",
              bar_format="{desc}: {n_fmt}/{total_fmt} [{elapsed}]") as bar:
        def stage(i: int) -> None:
            if i < len(stages):
                bar.set_description_str(f"reconstruct ({stages[i]})", refresh=False)
            if i:
                bar.update(1)
            else:
                bar.refresh()

        yield stage


def _model_for(local_weights, weights, options: ReconstructOptions):
    """`(params, config)` of the checkpoint with the options' preset and dtype applied."""
    params, config = load_model(local_weights, options.quiet, name=weights)
    if options.preset is not None:
        try:
            config = config.with_compression(options.preset)
        except ValueError as e:
            raise CLIError(one_line(e)) from None
    if options.points_from == "pointmap" and not config.enable_point:
        raise CLIError(f"checkpoint {weights} has no point head; use --points depth")
    if options.dtype != config.dtype:
        from rvggt_jax.weights.checkpoint import cast_params

        config, params = config.with_dtype(options.dtype), cast_params(params, options.dtype)
    return params, config


def _check_memory(config, shape: tuple[int, int, int], options: ReconstructOptions):
    """`(report, mesh)`: XLA's own plan of this forward for `shape` = (frames, height,
    width) (compiled, not run; the run uses the same compiled program), so that a forward
    that does not fit is refused before running rather than dying in the middle."""
    from rvggt_jax.planning.memory import InsufficientMemoryError, check_fits

    enable_compilation_cache()
    mesh = devices_mesh(options.devices)
    try:
        report = check_fits(config, *shape, param_dtype=options.dtype, mesh=mesh)
    except (InsufficientMemoryError, ValueError) as e:
        raise CLIError(str(e)) from None
    return report, mesh


def _decode(out: dict, images, chosen: list[Path], infos, options: ReconstructOptions):
    """The reconstruction (cameras, depth, points) of the model's outputs; its repairs
    are warnings."""
    from rvggt_jax.app.pipeline import reconstruction_from_outputs

    recon = reconstruction_from_outputs(out, images, names=[Path(p).name for p in chosen], infos=infos,
                                        points_from=options.points_from, conf_threshold=options.conf_threshold,
                                        max_points=options.max_points)
    for msg in recon.repairs:
        warn(msg)
    return recon


def _export(out_dir: Path, recon, source: Path, weights, config, options: ReconstructOptions) -> dict:
    from rvggt_jax.io.export import export_reconstruction

    meta = dict(source=str(source), weights=str(weights), preset=config.compression.name, mode=options.mode,
                conf_threshold=str(options.conf_threshold), points_from=options.points_from,
                exif_orientation=options.exif_orientation)
    return export_reconstruction(out_dir, recon, meta=meta,
                                 max_colmap_points=None if options.all_colmap_points else 100_000)


def _tell_summary(summary: dict, out_dir: Path, options: ReconstructOptions) -> None:
    """What the run wrote, and the warnings about it (no point kept, renamed images)."""
    if summary["points"] == 0:
        warn(f"no point passed the confidence threshold {options.conf_threshold}; points.ply is empty "
             f"(lower --conf-threshold, e.g. '0%')")
    if summary.get("colmap_renamed"):
        warn(f"COLMAP image names cannot contain spaces: {len(summary['colmap_renamed'])} name(s) written with "
             f"'_' in sparse/images.txt (e.g. {summary['colmap_renamed'][0][1]!r})")
    say(options.quiet, f"wrote {out_dir}: {summary['frames']} cameras, {summary['points']} points "
                       f"(confidence >= {summary['conf_threshold']:.4g}) in {summary['seconds']:.1f} s")


def demo(out_dir: str | Path = "rvggt_demo", options: ReconstructOptions = ReconstructOptions()) -> dict:
    """Run `reconstruct_folder` on the bundled images with the bundled random-weight model
    (`options`: those of `rvggt demo`, --preset, --dtype, --overwrite and --quiet)."""
    print(RANDOM_WEIGHTS_NOTICE, flush=True)
    if not DEMO_WEIGHTS.exists() or not DEMO_IMAGES.exists():
        raise CLIError(f"bundled demo data missing under {EXAMPLES_DIR} (broken install?)")
    summary = reconstruct_folder(DEMO_IMAGES, DEMO_WEIGHTS, out_dir, options)
    say(options.quiet, f"demo outputs in {out_dir} (random weights: meaningless geometry)")
    return summary
