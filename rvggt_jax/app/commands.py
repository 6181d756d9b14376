"""What `rvggt reconstruct` does (and `rvggt demo`, `rvggt_jax.app.demo`): inputs (a folder of images or a video)
-> the model (`rvggt_jax.app.pipeline`) -> every output file (`rvggt_jax.io.export`).

Order matters for the user: everything that can be checked cheaply (options, the input,
the output folder being writable and not holding another run) is checked before the
weights are loaded or downloaded and long before inference. Failures raise `CLIError`
(one line, see `rvggt_jax.app.messages`); warnings go to stderr as `rvggt: warning: ...`.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Sequence

from rvggt_jax.app.console import say, warn
from rvggt_jax.app.messages import CLIError, one_line
from rvggt_jax.app.model_runner import check_memory as _check_memory, model_for as _model_for, resolve_weights, run_model
from rvggt_jax.app.options import ReconstructOptions, check_one_size, select_frames

EXAMPLES_DIR = Path(__file__).resolve().parents[1] / "examples_data"  # rvggt_jax/examples_data
SAMPLE_IMAGES = EXAMPLES_DIR / "images"  # three small views the tests run the pipeline on
TINY_WEIGHTS = EXAMPLES_DIR / "tiny"  # the tiny RANDOM-weight model of the parity fixtures ("tiny-random")
FRAMES_DIR = "frames"  # video frames written here (the images the COLMAP model refers to)



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
    from rvggt_jax.app.outdir import OutputDirError, output_lock

    source, out_dir = Path(source), Path(out_dir)
    options.check()
    if options.ba is not None:
        from rvggt_jax.app.ba_command import check_ba_available

        check_ba_available()
    if options.loop_closure:
        import importlib.util

        if importlib.util.find_spec("gtsam") is None:  # said now, not after every chunk has run
            raise CLIError('--loop-closure needs gtsam (the pose graph): pip install "rvggt-jax[sequence]"')
    video = _check_source(source, options)
    _check_weights(weights)
    chosen = None if video else _image_inputs(source, options)
    if options.chunk_frames is not None and not video:
        from rvggt_jax.app.long_sequence import check_frame_order

        check_frame_order(chosen)
    if options.masks is not None:
        if video:
            raise CLIError("--masks takes masks named like the input images; the input is a video (extract its "
                           "frames to a folder first)")
        _mask_paths(chosen, options)  # a missing mask is said now, before the weights load
    created = not out_dir.exists()
    try:
        with output_lock(out_dir):
            return _reconstruct_locked(chosen, video, source, weights, out_dir, options, created)
    except OutputDirError as e:
        raise CLIError(str(e)) from None


def _reconstruct_locked(chosen, video: bool, source: Path, weights, out_dir: Path, options: ReconstructOptions,
                        created: bool) -> dict:
    """`reconstruct_folder` while it holds the output folder (`output_lock`)."""
    from rvggt_jax.app.outdir import Manifest, remove_if_unused

    resume = _resume_chunked(out_dir, options)
    if not resume:
        _prepare_output(out_dir, options)
    # a resumed chunked run's manifest also lists what the stopped run wrote
    manifest = Manifest(out_dir, carry=resume)
    try:
        # a hub repo id: download / convert now, before reading any input (a failure here
        # says what is missing without having made the user wait)
        local_weights = resolve_weights(weights, options.quiet)
        options = with_network_size(options, local_weights, weights)
        if video:
            chosen = _video_inputs(source, out_dir, options)
        if options.chunk_frames is not None:
            from rvggt_jax.app.long_sequence import reconstruct_chunked

            summary = reconstruct_chunked(chosen, source, weights, local_weights, out_dir, options, manifest)
            _tell_summary(summary, out_dir, options)
            return summary
        return _reconstruct(chosen, source, weights, local_weights, out_dir, options)
    finally:
        if not manifest.write() and created:  # also after a failure: the next --overwrite removes exactly these
            remove_if_unused(out_dir)  # a run that failed before writing anything leaves no folder behind


def with_network_size(options: ReconstructOptions, local_weights, name=None) -> ReconstructOptions:
    """`options` with its network size settled (`ReconstructOptions.size`): as given, else
    the width the checkpoint was trained at (its config.json's "train_image_size"), else
    upstream's 518."""
    import dataclasses

    from rvggt_jax.app.model_runner import trained_width
    from rvggt_jax.io.images import TARGET_SIZE

    if options.size is not None:
        return options
    size = trained_width(local_weights)
    if size is not None and size != TARGET_SIZE:
        say(options.quiet, f"network size {size}: the size {name or local_weights} was trained at (--size to change "
                           f"it)")
    return dataclasses.replace(options, size=size or TARGET_SIZE)


def _resume_chunked(out_dir: Path, options: ReconstructOptions) -> bool:
    """Whether this run continues a chunked run stopped in `out_dir` (same command, no
    --overwrite): its cached chunks are reused (their settings are checked against this
    run's before any is read, `long_sequence.check_run_file`)."""
    from rvggt_jax.app.long_sequence import resumable

    if options.chunk_frames is None or options.overwrite or not resumable(out_dir):
        return False
    say(options.quiet, f"{out_dir} holds a chunked run: continuing it (--overwrite starts over)")
    return True


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
    by `resolve_weights`."""
    from rvggt_jax.weights.hub import is_repo_id
    from rvggt_jax.weights.pretrained import BUNDLED

    if str(weights) in BUNDLED:
        return
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


_STAGES = ("loading weights", "checking memory", "running the model", "decoding cameras", "writing outputs")


def _reconstruct(chosen, source: Path, weights, local_weights, out_dir: Path, options: ReconstructOptions) -> dict:
    """`reconstruct_folder` once the inputs are chosen and the output folder is ready:
    load the images, then the model, check the memory, run, decode, write (then, with
    --ba, bundle-adjust: `rvggt_jax.app.ba_command`)."""
    from rvggt_jax.io.images import network_images

    if options.ba is not None and len(chosen) < 2:
        raise CLIError(f"--ba (bundle adjustment) needs at least 2 images; got {len(chosen)}")
    images, infos, chosen = _load_inputs(chosen, options)
    if options.shared_camera:
        check_one_size(infos)
    s, _, h, w = images.shape
    masks = None
    if options.masks is not None:
        from rvggt_jax.app.pipeline import apply_masks

        masks = _load_masks(chosen, infos, (h, w), options)
        images = apply_masks(images, masks)
    t0 = time.perf_counter()
    stages = _STAGES + (("bundle adjustment",) if options.ba is not None else ())
    with _stage_bar(stages, options.quiet) as stage:
        stage(0)
        params, config = _model_for(local_weights, weights, options)
        if options.ba is not None:
            from rvggt_jax.app.ba_command import split_track_head

            params, track_params = split_track_head(params, config, weights)
        stage(1)
        # the images go in as uint8 (exact, `network_images`, made once here): plan,
        # compile and run for that
        net = network_images(images)
        report, mesh = _check_memory(config, (s, h, w), options, net.dtype)
        stage(2)
        out = run_model(params, net, config, weights, compiled=report.compiled, mesh=mesh)
        stage(3)
        recon = _decode(out, images, chosen, infos, options, masks)
        stage(4)
        summary = _export(out_dir, recon, source, weights, config, options, chosen, model_outputs=out)
        if options.ba is not None:
            from rvggt_jax.app.ba_command import run_bundle_adjustment

            stage(5)
            summary["ba"] = run_bundle_adjustment(out_dir, recon, track_params, config, options)
        stage(len(stages))
    summary["seconds"] = time.perf_counter() - t0
    _tell_summary(summary, out_dir, options)
    if "ba" in summary:
        from rvggt_jax.app.ba_command import tell_bundle_adjustment

        tell_bundle_adjustment(summary["ba"], out_dir, options.quiet)
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
            images, infos = load_images_with_info(chosen, mode=options.mode, progress=progress, target=options.size,
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


def _mask_paths(chosen: list[Path], options: ReconstructOptions) -> list[Path]:
    """The mask file of each chosen image (`--masks`); `CLIError` naming a missing one."""
    from rvggt_jax.io.masks import MaskError, find_masks

    try:
        return find_masks(chosen, options.masks)
    except MaskError as e:
        raise CLIError(f"--masks: {e}") from None


def _load_masks(chosen: list[Path], infos, image_hw: tuple[int, int], options: ReconstructOptions):
    """Masks [S, H, W] bool of the loaded images, preprocessed as they were; `CLIError`
    naming a mask of the wrong size."""
    from rvggt_jax.io.masks import MaskError, load_masks

    try:
        masks = load_masks(_mask_paths(chosen, options), infos, image_hw, options.mode,
                           exif_orientation=options.exif_orientation, target=options.size)
    except MaskError as e:
        raise CLIError(f"--masks: {e}") from None
    kept = float(masks.mean()) if masks.size else 0.0
    if kept == 0.0:  # else the run ends with "no point passed the confidence threshold", a wrong hint
        raise CLIError(f"--masks: the masks in {options.masks} keep no pixel of any image (all black, or only over "
                       f"padding); white marks what to keep")
    say(options.quiet, f"masks: keeping {100 * kept:.1f}% of the network input's pixels")
    return masks


def _decode(out: dict, images, chosen: list[Path], infos, options: ReconstructOptions, masks=None):
    """The reconstruction (cameras, depth, points) of the model's outputs, masked pixels
    left out (`masks` [S, H, W], True = keep); its repairs are warnings."""
    from rvggt_jax.app.pipeline import reconstruction_from_outputs

    recon = reconstruction_from_outputs(out, images, names=[Path(p).name for p in chosen], infos=infos,
                                        points_from=options.points_from, conf_threshold=options.conf_threshold,
                                        max_points=options.max_points, masks=masks)
    for msg in recon.repairs:
        warn(msg)
    return recon


def _export(out_dir: Path, recon, source: Path, weights, config, options: ReconstructOptions,
            image_paths: Sequence[Path] | None = None, model_outputs=None) -> dict:
    """Every output file (`rvggt_jax.io.export`); `model_outputs`: the forward's outputs,
    for --save-raw."""
    from rvggt_jax.io.export import export_reconstruction

    meta = dict(source=str(source), weights=str(weights), preset=config.compression.name, mode=options.mode,
                conf_threshold=str(options.conf_threshold), points_from=options.points_from,
                exif_orientation=options.exif_orientation)
    return export_reconstruction(out_dir, recon, meta=meta, image_paths=image_paths,
                                 max_colmap_points=None if options.all_colmap_points else 100_000,
                                 camera_model=options.camera_type, shared_camera=options.shared_camera,
                                 save_raw=options.save_raw, model_outputs=model_outputs)


def _tell_summary(summary: dict, out_dir: Path, options: ReconstructOptions) -> None:
    """What the run wrote, and the warnings about it (no point kept, renamed images)."""
    if summary["points"] == 0:
        warn(f"no point passed the confidence threshold {options.conf_threshold}; points.ply is empty "
             f"(lower --conf-threshold, e.g. '0%')")
    if summary.get("colmap_renamed"):
        warn(f"COLMAP image names cannot contain spaces: {len(summary['colmap_renamed'])} name(s) written with "
             f"'_' in sparse/images.txt (e.g. {summary['colmap_renamed'][0][1]!r})")
    chunks = f" from {summary['chunks']} chunks" if "chunks" in summary else ""
    say(options.quiet, f"wrote {out_dir}: {summary['frames']} cameras{chunks}, {summary['points']} points "
                       f"(confidence >= {summary['conf_threshold']:.4g}) in {summary['seconds']:.1f} s")
