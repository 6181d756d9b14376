"""`rvggt`: command-line front end (argument parsing, messages, error mapping; the work is
in `rvggt_jax.app.commands`, `rvggt_jax.app.pipeline` and `rvggt_jax.io`).

    rvggt convert SRC DST [...]           upstream .safetensors -> Orbax (`rvggt_jax.app.convert_command`)
    rvggt reconstruct INPUT --weights CKPT --out OUT_DIR [options]
                                          INPUT: a folder of images or a video file;
                                          CKPT: a local checkpoint or a hub repo id
                                          (facebook/VGGT-1B: downloaded, converted once)
    rvggt view OUT_DIR [--port P]         interactive 3D viewer (viser) on localhost;
          [--weights CKPT]                with an upload form that reconstructs new images
    rvggt demo [--out DIR] [--ba]         the whole pipeline on a bundled held-out procedural
                                          scene with rvggt-small, the small VGGT trained
                                          here, and its errors against the true cameras
    rvggt finetune DATA_DIR --out DIR     fine-tune on images + cameras (+ depth); see
                                          docs/training.md (`rvggt_jax.train`)
    rvggt train-small --out DIR           train the shipped small model ("rvggt-small")
                                          from scratch on procedural scenes; resumable
    rvggt analyze IMAGES --weights CKPT --out DIR
                                          the paper's diagnostics: attention rank per
                                          layer, saliency and K/V coverage maps
    rvggt calibrate SCENE... --out DIR    a band schedule fitted to a model and data, as a
                                          preset file for --preset path.json
                                          (`rvggt_jax.app.diagnostics_command`)
    rvggt plan --frames N --target T      will it fit? XLA's memory plan for a GPU or TPU
                                          that need not be here (exit 0 fits, 3 does not;
                                          `rvggt_jax.app.plan_command`)
    rvggt --version

`reconstruct` writes, in OUT_DIR: points.ply, scene.glb, cameras.json, sparse/*.txt
(COLMAP text model), depth/<stem>.png (+ depth/depth_scale.json), depth_preview/,
thumbnails/, trajectory.png (and frames/ for a video, predictions.npz with --save-raw); see
`rvggt_jax.io.export`. With --ba (bundle adjustment, the `[ba]` extra: pycolmap) also
sparse_ba/ (COLMAP model with tracks: text, and binary in sparse_ba/bin), cameras_ba.json,
points_ba.ply and ba_report.json (reprojection errors before / after); see `rvggt_jax.ba`.

Failures exit non-zero with `rvggt: error: ...` on stderr, details indented under it
(set RVGGT_DEBUG=1 for the traceback). Compiled programs are cached across runs in
$RVGGT_CACHE_DIR (default ~/.cache/rvggt-jax/xla; RVGGT_CACHE_DIR=off disables it).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Sequence

# nothing here imports JAX: `main` sets up the process before anything does (the commands
# are imported by the functions that run them)
from rvggt_jax.app.messages import CLIError, format_error, one_line
from rvggt_jax.app.console import PROG
from rvggt_jax.app.options import ReconstructOptions, known_presets



_DEFAULTS = ReconstructOptions()


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are one line too."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise CLIError(f"{message} (see `{self.prog} --help`)", code=2)


# ---------------------------------------------------------------------------------------
# convert
# ---------------------------------------------------------------------------------------


def _convert(argv: Sequence[str]) -> int:
    """`rvggt convert ...` = the converter's own command line (`python convert/convert_checkpoint.py`)."""
    try:
        from rvggt_jax.app.convert_command import main as entry
    except ImportError as e:
        raise CLIError(f"the converter is not installed ({one_line(e)})") from None
    return int(entry(list(argv), prog=f"{PROG} convert") or 0)


# ---------------------------------------------------------------------------------------
# argument parsing
# ---------------------------------------------------------------------------------------


def _positive_float(text: str) -> float:
    import math

    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def _port(text: str) -> int:
    """A TCP port, 1-65535 (viser's thread would fail on any other and the command hang)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 1-65535, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    from rvggt_jax import __version__
    from rvggt_jax.app.demo import DEMO_NOTICE

    parser = _Parser(prog=PROG, description="VGGT feed-forward 3D reconstruction in JAX.")
    parser.add_argument("--version", action="version", version=f"{PROG} (rvggt-jax) {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    p = sub.add_parser("convert", help="convert an upstream VGGT checkpoint (.safetensors) to rvggt-jax (Orbax)",
                       add_help=False)
    p.add_argument("args", nargs=argparse.REMAINDER, help="SRC DST [converter options]; see `rvggt convert --help`")

    presets = ", ".join(known_presets())
    _add_reconstruct_parser(sub, presets)

    p = sub.add_parser("view", help="interactive 3D viewer of a reconstruction (in the browser, localhost)",
                       description="Serve an interactive viewer of OUT_DIR (points with a confidence slider, camera "
                                   "frustums with their images, frame selection, a black / white background "
                                   "filter, points from depth or the point map with predictions.npz of --save-raw; "
                                   "with --weights, an upload form that reconstructs new images) on "
                                   "http://localhost:PORT.")
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder written by `rvggt reconstruct`")
    p.add_argument("--port", type=_port, default=8080, help="port on localhost, 1-65535 (default %(default)s)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default %(default)s: this machine only)")
    p.add_argument("--weights", default=None, metavar="CKPT",
                   help="also offer an upload form in the page: images (or a .zip of them, or a video) uploaded "
                        "there are reconstructed on this machine with CKPT (as `rvggt reconstruct --weights CKPT "
                        "--save-raw`) into a new folder of --work-dir, then shown; anyone who can open the page "
                        "can run it (mind --host)")
    p.add_argument("--work-dir", default=None, metavar="DIR",
                   help="with --weights: where the uploads and their reconstructions go, DIR/upload_001/{input,"
                        "reconstruction}, ... (default rvggt_uploads)")

    p = sub.add_parser("demo", help="reconstruct a bundled held-out scene with the bundled trained small model",
                       description=DEMO_NOTICE)
    p.add_argument("--out", default="rvggt_demo", metavar="DIR", help="output folder (default %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier demo run in DIR")
    p.add_argument("--ba", action="store_true",
                   help="also bundle-adjust the cameras with the model's tracks (the [ba] extra: pycolmap) and "
                        "report the reprojection error before and after")
    _view_options(p)
    _common_options(p, presets)

    from rvggt_jax.app.eval_command import add_eval_parser
    from rvggt_jax.app.finetune_command import add_finetune_parser, add_train_small_parser
    from rvggt_jax.app.plan_command import add_plan_parser
    from rvggt_jax.app.diagnostics_command import add_diagnostics_parsers

    add_eval_parser(sub)
    add_diagnostics_parsers(sub)
    add_finetune_parser(sub)
    add_train_small_parser(sub)
    add_plan_parser(sub)
    return parser


def _add_reconstruct_parser(sub, presets: str) -> None:
    """`rvggt reconstruct`: its defaults are `ReconstructOptions`'."""
    p = sub.add_parser("reconstruct", help="reconstruct a folder of images or a video",
                       description="Reconstruct cameras, depth and a point cloud from the images of a folder "
                                   "(sorted by name; other files are skipped) or the frames of a video.")
    p.add_argument("images_dir", metavar="INPUT",
                   help="folder of images (png, jpg, ...) or a video file (mp4, mov, mkv, webm, ...)")
    p.add_argument("--weights", required=True, metavar="CKPT",
                   help="checkpoint: a Hugging Face repo id (facebook/VGGT-1B: downloaded into the hub cache and "
                        "converted once under ~/.cache/rvggt-jax), a folder with model.safetensors "
                        "[+ config.json], a .safetensors file, or a converted (Orbax) folder")
    p.add_argument("--out", required=True, metavar="OUT_DIR",
                   help="output folder (created; must be empty unless --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="reuse a non-empty output folder: delete the files the previous rvggt run there wrote "
                        "(listed in its .rvggt-manifest.json) and nothing else")
    _common_options(p, presets)
    _view_options(p)
    p.add_argument("--mode", default=_DEFAULTS.mode, choices=("crop", "pad"),
                   help="crop: width 518, height centre-cropped to <= 518 (default); "
                        "pad: longest side 518, white-padded to square (518: see --size)")
    p.add_argument("--size", type=int, default=None, metavar="N",
                   help="network size in place of 518 (crop: the width; pad: the longest side), a multiple of 14; "
                        "default: the size the checkpoint was trained at when its config.json records it "
                        "(rvggt-small: 112), else 518")
    p.add_argument("--conf-threshold", default=_DEFAULTS.conf_threshold, metavar="X",
                   help="keep points whose confidence is >= X (VGGT confidences are >= 1), or, written "
                        "'P%%', at or above the P-th percentile of all confidences (default %(default)s; "
                        "'0%%' keeps every point)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="use at most N images (or video frames), evenly spaced")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--every", type=int, default=None, metavar="N",
                   help="video: keep every N-th frame")
    g.add_argument("--fps", type=_positive_float, default=None, metavar="F",
                   help="video: keep F frames per second (default for a video: 1)")
    p.add_argument("--skip-bad", action="store_true",
                   help="leave out images that cannot be read, with a warning naming each (default: stop)")
    p.add_argument("--masks", default=None, metavar="DIR",
                   help="per-image masks in DIR, named like the images (same file stem, any image format; "
                        "white = keep): masked pixels are set to 0 before the forward and their points and "
                        "depth are left out of every output")
    p.add_argument("--ignore-exif", action="store_true",
                   help="read images as stored, ignoring their EXIF orientation (upstream's behaviour)")
    p.add_argument("--points", default=_DEFAULTS.points_from, choices=("depth", "pointmap"),
                   help="point cloud from the depth maps unprojected with the predicted cameras "
                        "(default) or from the point-map head")
    p.add_argument("--max-points", type=int, default=_DEFAULTS.max_points, metavar="N",
                   help="cap on the points written to points.ply (random subset; default %(default)s)")
    p.add_argument("--all-colmap-points", action="store_true",
                   help="write every point of points.ply to sparse/points3D.txt (default: a random subset of "
                        "at most 100000)")
    from rvggt_jax.io.colmap import CAMERA_MODELS

    p.add_argument("--camera-type", default=_DEFAULTS.camera_type, type=str.upper, choices=tuple(CAMERA_MODELS),
                   help="camera model of the COLMAP model (sparse/, and sparse_ba/ with --ba): PINHOLE (fx, fy, cx, "
                        "cy; default), SIMPLE_PINHOLE (f = (fx + fy) / 2, cx, cy) or SIMPLE_RADIAL (f, cx, cy, k = 0)")
    p.add_argument("--shared-camera", action="store_true",
                   help="one COLMAP camera for all images (the median intrinsics; --ba refines that one): images of "
                        "one size, e.g. a phone video")
    p.add_argument("--save-raw", action="store_true",
                   help="also write predictions.npz: the model's outputs under upstream VGGT's names (extrinsic, "
                        "intrinsic, depth, depth_conf, world_points, ..., image_names; rvggt_jax.io.raw)")
    p.add_argument("--devices", type=int, default=None, metavar="N",
                   help="split the frames over N local devices, one forward pass (default: all of them when "
                        "there are several)")
    p.add_argument("--low-memory", action="store_true",
                   help="the low-memory inference mode (VGGTConfig.with_low_memory: depth and points in float16, "
                        "confidences in bfloat16, the camera head's weights in --dtype, coarse layers kept "
                        "reassembled); as `rvggt plan --low-memory` plans it")
    _add_chunk_options(p)
    _add_ba_options(p)


def _chunk_frames(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of frames or 'auto', got {text!r}") from None


def _add_chunk_options(p: argparse.ArgumentParser) -> None:
    """--chunk-frames, --overlap, --loop-closure (`rvggt_jax.app.long_sequence`)."""
    g = p.add_argument_group("long sequences (frames in capture order: a video, or files named in order)")
    g.add_argument("--chunk-frames", type=_chunk_frames, default=None, metavar="C|auto",
                   help="predict the frames in chunks of C (auto: the largest the device fits), chained by Sim(3) "
                        "on the frames consecutive chunks share; chunks are cached in OUT/chunks/ and a stopped "
                        "run resumes; the point cloud is voxel-averaged to at most --max-points")
    g.add_argument("--overlap", type=int, default=None, metavar="O",
                   help="frames consecutive chunks share (default: a quarter of the chunk)")
    g.add_argument("--loop-closure", action="store_true",
                   help="close loops: revisits found from the frames' DINOv2 descriptors, verified by a forward "
                        "over both places, all chunks' Sim(3)s optimised as a pose graph (gtsam: pip install "
                        "\"rvggt-jax[sequence]\")")


def _add_ba_options(p: argparse.ArgumentParser) -> None:
    """--ba and its --ba-* options (defaults: `rvggt_jax.ba.refine.BAOptions`'; given without
    --ba they are an error, see `_ba_options`)."""
    from rvggt_jax.ba.refine import BAOptions

    d = BAOptions()
    g = p.add_argument_group("bundle adjustment (needs pycolmap: pip install \"rvggt-jax[ba]\")")
    g.add_argument("--ba", action="store_true",
                   help="refine the predicted cameras by bundle adjustment of the track head's tracks (pycolmap); "
                        "writes sparse_ba/ (COLMAP model with tracks), cameras_ba.json, points_ba.ply and ba_report.json")
    g.add_argument("--ba-query-frames", type=int, default=None, metavar="N",
                   help=f"frames to take query points in, evenly spaced, frame 0 first; each costs a forward pass "
                        f"with the track head (default {d.query_frames})")
    g.add_argument("--ba-query-points", type=int, default=None, metavar="N",
                   help=f"query points in all, split over the query frames (default {d.query_points})")
    g.add_argument("--ba-keypoints", default=None, choices=("sift", "grid"),
                   help=f"query points: SIFT keypoints ranked by depth confidence, topped up with grid points, or "
                        f"the most confident pixel of each grid cell (default {d.keypoints})")
    g.add_argument("--ba-vis-threshold", type=float, default=None, metavar="X",
                   help=f"keep a track's observation when the tracker's visibility is >= X in [0, 1] "
                        f"(default {d.vis_threshold})")
    g.add_argument("--ba-conf-threshold", type=float, default=None, metavar="X",
                   help=f"keep a track's observation when the tracker's confidence is >= X in [0, 1] "
                        f"(default {d.conf_threshold})")
    g.add_argument("--ba-max-error", type=float, default=None, metavar="PX",
                   help=f"drop observations reprojecting more than PX network pixels from their triangulated "
                        f"point (default {d.max_error:g})")
    g.add_argument("--ba-refine-focal", action="store_true",
                   help="also refine each frame's focal lengths (default: poses and points only)")


_BA_FIELDS = {"ba_query_frames": "query_frames", "ba_query_points": "query_points", "ba_keypoints": "keypoints",
              "ba_vis_threshold": "vis_threshold", "ba_conf_threshold": "conf_threshold",
              "ba_max_error": "max_error"}


def _ba_options(args: argparse.Namespace):
    """The `BAOptions` of --ba and its --ba-* options (None without --ba; a --ba-* option
    without --ba is a usage error rather than silently ignored)."""
    from rvggt_jax.ba.refine import BAOptions

    given = {field: getattr(args, arg) for arg, field in _BA_FIELDS.items() if getattr(args, arg) is not None}
    if args.ba_refine_focal:
        given["refine_focal"] = True
    if not args.ba:
        if given:
            names = [f"--{a.replace('_', '-')}" for a in _BA_FIELDS if getattr(args, a) is not None]
            names += ["--ba-refine-focal"] if args.ba_refine_focal else []
            raise CLIError(f"{', '.join(names)} only apply with --ba")
        return None
    return BAOptions(**given)


def _view_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--view", action="store_true",
                   help="then serve the interactive viewer on the result (as `rvggt view OUT`; Ctrl-C stops it)")
    p.add_argument("--port", type=_port, default=8080, help="the viewer's port on localhost with --view (default "
                                                            "%(default)s)")


def _check_view(args: argparse.Namespace) -> None:
    """--view's port is checked before the reconstruction runs (not found taken after it)."""
    if args.command in ("reconstruct", "demo") and getattr(args, "view", False):
        from rvggt_jax.app.viewer import ViewerError, check_bindable

        try:
            check_bindable("127.0.0.1", args.port)
        except ViewerError as e:
            raise CLIError(f"--view: {e}") from None
    elif args.command in ("reconstruct", "demo") and args.port != 8080:
        raise CLIError("--port applies with --view")


def _common_options(p: argparse.ArgumentParser, presets: str) -> None:
    p.add_argument("--preset", default=None, metavar="NAME|FILE",
                   help=f"compression preset of the global attention ({presets}), or a preset file path.json "
                        f"(written by `rvggt calibrate`); default: the checkpoint's")
    p.add_argument("--dtype", default=_DEFAULTS.dtype, choices=("float32", "bfloat16"),
                   help="compute dtype of the aggregator (bfloat16: upstream's mixed precision, about half "
                        "the memory; the heads stay float32; default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or messages (errors and warnings only)")


def reconstruct_options(args: argparse.Namespace) -> ReconstructOptions:
    """The `ReconstructOptions` of a parsed `rvggt reconstruct` or `rvggt demo` (which has
    only --preset, --dtype, --overwrite and --quiet: the others keep their defaults)."""
    common = dict(preset=args.preset, dtype=args.dtype, overwrite=args.overwrite, quiet=args.quiet)
    if args.command == "demo":
        from rvggt_jax.ba.refine import BAOptions

        return ReconstructOptions(**common, ba=BAOptions() if args.ba else None)
    return ReconstructOptions(
        **common, mode=args.mode, size=args.size, max_frames=args.max_frames, every=args.every, fps=args.fps,
        skip_bad=args.skip_bad, exif_orientation=not args.ignore_exif, masks=args.masks, devices=args.devices,
        conf_threshold=args.conf_threshold, points_from=args.points, max_points=args.max_points,
        all_colmap_points=args.all_colmap_points, camera_type=args.camera_type, shared_camera=args.shared_camera,
        save_raw=args.save_raw, ba=_ba_options(args), chunk_frames=args.chunk_frames, low_memory=args.low_memory,
        overlap=args.overlap, loop_closure=args.loop_closure)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `rvggt` console script; returns the exit status."""
    from rvggt_jax.app.host_heap import keep_freed_host_memory
    from rvggt_jax.app import xla_cpu

    argv = list(sys.argv[1:] if argv is None else argv)
    # before anything imports JAX: no probing of absent accelerators, and on the CPU alone
    # no CUDA plugin (it logs "Could not find cuda drivers" lines; `plan` compiles with
    # it); multi-threaded CPU convolutions; each run reusing the host memory the last freed
    xla_cpu.use_cpu_without_accelerator()
    if argv[:1] != ["plan"]:
        xla_cpu.leave_cuda_plugin_unloaded()
    xla_cpu.prefer_threaded_convolutions()
    keep_freed_host_memory()
    try:
        if argv and argv[0] == "convert":
            return _convert(argv[1:])
        args = build_parser().parse_args(argv)
        if args.command is None:
            build_parser().print_help()
            return 2
        from rvggt_jax.app.commands import reconstruct_folder
        from rvggt_jax.app.demo import demo

        _check_view(args)
        if args.command == "reconstruct":
            reconstruct_folder(args.images_dir, args.weights, args.out, reconstruct_options(args))
        elif args.command == "view":
            from rvggt_jax.app.viewer import serve

            serve(args.out_dir, port=args.port, host=args.host, weights=args.weights, work_dir=args.work_dir)
        elif args.command == "demo":
            demo(args.out, reconstruct_options(args))
        if args.command in ("reconstruct", "demo") and args.view:
            from rvggt_jax.app.viewer import serve

            serve(args.out, port=args.port)
        elif args.command == "eval":
            from rvggt_jax.app.eval_command import run_eval_command

            run_eval_command(args)
        elif args.command == "finetune":
            from rvggt_jax.app.finetune_command import run_finetune_command

            run_finetune_command(args)
        elif args.command == "train-small":
            from rvggt_jax.app.finetune_command import run_train_small_command

            run_train_small_command(args)
        elif args.command in ("analyze", "calibrate"):
            from rvggt_jax.app import diagnostics_command as diag

            run = diag.run_analyze_command if args.command == "analyze" else diag.run_calibrate_command
            return run(args)
        elif args.command == "plan":
            from rvggt_jax.app.plan_command import run_plan_command

            return run_plan_command(args)
        return 0
    except CLIError as e:
        if os.environ.get("RVGGT_DEBUG"):
            raise
        print(format_error(PROG, str(e)), file=sys.stderr, flush=True)
        return e.code
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr, flush=True)
        from rvggt_jax.app.model_runner import ABANDONED_FORWARD

        if ABANDONED_FORWARD.is_set():  # XLA cannot cancel it, and exiting would wait for it
            sys.stdout.flush()
            os._exit(130)
        return 130
    except MemoryError:
        print(f"{PROG}: error: out of memory (use fewer frames with --max-frames or a compression --preset)",
              file=sys.stderr)
        return 1
    except Exception as e:  # one line, no traceback, for anything unexpected
        if os.environ.get("RVGGT_DEBUG"):
            raise
        msg = one_line(e)
        if "RESOURCE_EXHAUSTED" in msg or "out of memory" in msg.lower():
            msg = "out of memory (use fewer frames with --max-frames or a compression --preset): " + msg[:300]
        print(f"{PROG}: error: {type(e).__name__}: {msg} (set RVGGT_DEBUG=1 for the traceback)",
              file=sys.stderr, flush=True)
        return 1


if __name__ == "__main__":
    sys.exit(main())
