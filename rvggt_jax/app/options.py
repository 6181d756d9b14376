"""The options of `rvggt reconstruct` and `rvggt demo` (`ReconstructOptions`), with the
command line's defaults and the checks that run before anything slow."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

from rvggt_jax.app.messages import CLIError

DEFAULT_CONF_THRESHOLD = "50%"


def known_presets() -> tuple[str, ...]:
    from rvggt_jax.compression.config import PRESETS

    return tuple(PRESETS)


def check_preset(value: str) -> None:
    """A --preset value: a known name, or a preset file that exists and parses (its depth
    is checked against the model's later, when the model is loaded). `CLIError` else."""
    from rvggt_jax.diagnostics.presets_io import PresetError, is_preset_path, load_preset

    if is_preset_path(value):
        try:
            load_preset(value)
        except PresetError as e:
            raise CLIError(str(e)) from None
    elif value not in known_presets():
        raise CLIError(f"unknown preset {value!r}; known presets: {', '.join(known_presets())}, or a preset file "
                       f"path.json")


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


def check_one_size(infos) -> None:
    """`CLIError` naming two of the sizes when the images (anything with `name`, `width`,
    `height`: `ImageInfo`s) differ in size: one shared camera cannot have both (said
    before the model runs)."""
    first = infos[0]
    other = next((i for i in infos if (i.width, i.height) != (first.width, first.height)), None)
    if other is not None:
        raise CLIError(f"--shared-camera needs images of one size; got {first.width}x{first.height} ({first.name}) "
                       f"and {other.width}x{other.height} ({other.name})")


@dataclasses.dataclass(frozen=True, kw_only=True)
class ReconstructOptions:
    """How `rvggt reconstruct` (and `rvggt demo`) run: the command line's options, with its
    defaults. The CLI builds one from the parsed arguments; `reconstruct_folder` checks it
    (`check`) before it looks at anything else.

    Inputs:
      mode: "crop" (width 518, height centre-cropped to <= 518) or "pad" (longest side
        518, white-padded to square).
      size: the network size in place of 518 (crop: the width; pad: the longest side), a
        multiple of 14; None: the size the checkpoint was trained at when its config.json
        records one ("train_image_size": the bundled rvggt-small's 84 x 112 gives 112),
        else 518.
      max_frames: use at most this many images (or video frames), evenly spaced; None: all.
      every / fps: a video's frames to keep, every N-th or F per second (at most one of
        them; neither: 1 per second). Refused for a folder of images.
      skip_bad: leave out images that cannot be read (a warning names each) instead of
        stopping at the first.
      exif_orientation: apply the EXIF orientation of photos (False: read them as stored,
        upstream's behaviour).
      masks: a folder with one mask per image, by file stem (white = keep): masked pixels
        are 0 in the network input and have no point or depth in any output
        (`rvggt_jax.io.masks`); None: no masks. Images only, not a video.
    Model:
      preset: compression preset of the global attention (`known_presets()`) or a preset
        file path.json (`rvggt_jax.diagnostics.load_preset`); None: the checkpoint's.
      dtype: the aggregator's compute dtype, "float32" or "bfloat16" (the heads stay float32).
      low_memory: the low-memory inference mode (`VGGTConfig.with_low_memory`: 16-bit
        outputs, the camera head's weights in the compute dtype, coarse layers kept
        reassembled), for long sequences on small cards.
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
      camera_type: the COLMAP model's camera model (sparse/, and sparse_ba/ with `ba`):
        "PINHOLE" (fx, fy, cx, cy), "SIMPLE_PINHOLE" (f = (fx + fy) / 2, cx, cy) or
        "SIMPLE_RADIAL" (f, cx, cy, k = 0).
      shared_camera: one COLMAP camera for all images (the median intrinsics; bundle
        adjustment refines that one): images of one size only (a video, one camera's
        photos). cameras.json keeps each frame's predicted camera.
      save_raw: also write predictions.npz, the model's outputs under upstream's names
        (`rvggt_jax.io.raw`).
      overwrite: reuse a non-empty output folder, deleting the files the previous rvggt run
        there wrote (its manifest) and nothing else.
      quiet: no progress bars or messages (errors and warnings only).
    Long sequences (`rvggt_jax.app.long_sequence`):
      chunk_frames: predict the frames in chunks of this many (an int >= 2, or "auto": the
        largest chunk the device's memory plan fits), aligned by Sim(3) on the frames
        consecutive chunks share; None: one forward over every frame.
      overlap: frames consecutive chunks share (>= 1, < chunk_frames; None: a quarter
        of the chunk).
      loop_closure: detect revisits from the frames' place descriptors, verify each with
        a forward over both places, and optimise the chunks' Sim(3)s as a pose graph.
    Refinement:
      ba: bundle-adjust the predicted cameras with the track head's tracks and pycolmap
        (`rvggt_jax.ba.refine.BAOptions`: query frames and points, track filters, ...);
        None: no bundle adjustment. Needs the `[ba]` extra (pycolmap).
    """

    mode: str = "crop"
    size: int | None = None
    max_frames: int | None = None
    every: int | None = None
    fps: float | None = None
    skip_bad: bool = False
    exif_orientation: bool = True
    masks: str | Path | None = None
    preset: str | None = None
    dtype: str = "float32"
    low_memory: bool = False
    devices: int | None = None
    conf_threshold: str | float = DEFAULT_CONF_THRESHOLD
    points_from: str = "depth"
    max_points: int | None = 2_000_000
    all_colmap_points: bool = False
    camera_type: str = "PINHOLE"
    shared_camera: bool = False
    save_raw: bool = False
    overwrite: bool = False
    quiet: bool = False
    chunk_frames: int | str | None = None
    overlap: int | None = None
    loop_closure: bool = False
    ba: "BAOptions | None" = None  # noqa: F821 - rvggt_jax.ba.refine.BAOptions, imported when used

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
        if self.size is not None and (isinstance(self.size, bool) or not isinstance(self.size, int)
                                      or self.size < 14 or self.size % 14):
            raise CLIError(f"--size must be a positive multiple of 14 (the patch size); got {self.size}")
        if self.max_frames is not None and self.max_frames < 1:
            raise CLIError(f"--max-frames must be at least 1; got {self.max_frames}")
        if self.preset is not None:
            check_preset(self.preset)
        if self.dtype not in ("float32", "bfloat16"):
            raise CLIError(f"unknown dtype {self.dtype!r}; use float32 or bfloat16")
        if self.max_points is not None and self.max_points < 1:
            raise CLIError(f"--max-points must be at least 1; got {self.max_points}")
        if self.points_from not in ("depth", "pointmap"):
            raise CLIError(f"unknown point source {self.points_from!r}; use depth or pointmap")
        from rvggt_jax.io.colmap import CAMERA_MODELS

        if self.camera_type not in CAMERA_MODELS:
            raise CLIError(f"unknown --camera-type {self.camera_type!r}; use {', '.join(CAMERA_MODELS)}")
        if self.every is not None and self.fps is not None:
            raise CLIError("give --every or --fps, not both")
        if self.every is not None and self.every < 1:
            raise CLIError(f"--every must be at least 1; got {self.every}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise CLIError(f"--fps must be a positive number; got {self.fps}")
        self._check_chunking()
        if self.ba is not None:
            try:
                self.ba.check()
            except ValueError as e:
                raise CLIError(str(e)) from None

    def _check_chunking(self) -> None:
        c, o = self.chunk_frames, self.overlap
        if c is not None:
            # the chunks' raw predictions are the cache itself (OUT/chunks/chunk_*/*.npy): one
            # predictions.npz of every frame would hold the whole sequence in memory
            if self.save_raw:
                raise CLIError("--save-raw does not run with --chunk-frames: each chunk's predictions are kept in "
                               "OUT/chunks/chunk_*/ (depth.npy, confidence.npy, extrinsics.npy, ...); drop --save-raw")
        if c is None:
            given = [n for n, v in (("--overlap", o is not None), ("--loop-closure", self.loop_closure)) if v]
            if given:
                raise CLIError(f"{' and '.join(given)} only appl{'y' if len(given) > 1 else 'ies'} with --chunk-frames "
                               f"(e.g. --chunk-frames 60 {' '.join(given)}{' 10' if o is not None else ''})")
            return
        if c != "auto" and (isinstance(c, bool) or not isinstance(c, int) or c < 2):
            raise CLIError(f"--chunk-frames must be at least 2 (or auto); got {c} (e.g. --chunk-frames 60)")
        if o is not None and o < 1:
            raise CLIError(f"--overlap must be at least 1: consecutive chunks are aligned on the frames they share; "
                           f"got {o} (e.g. --overlap {max(1, c // 4) if isinstance(c, int) else 10})")
        if o is not None and isinstance(c, int) and o >= c:
            raise CLIError(f"--overlap must be smaller than --chunk-frames {c}; got {o} (e.g. --overlap "
                           f"{max(1, c // 4)})")
        if self.ba is not None:
            raise CLIError("--ba does not run with --chunk-frames yet (bundle adjustment needs every frame in one "
                           "forward); drop one of them")
