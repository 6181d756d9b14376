"""`rvggt`: command-line front end.

    rvggt convert SRC DST [...]           upstream checkpoint -> our format (see `convert`)
    rvggt reconstruct IMAGES_DIR --weights CKPT --out OUT_DIR [options]
    rvggt demo [--out DIR]                the whole pipeline on bundled images with a
                                          tiny RANDOM-weight model (seconds)

`reconstruct` writes, in OUT_DIR: points.ply, cameras.json, sparse/*.txt (COLMAP
text model), depth/<stem>.png (+ depth/depth_scale.json), depth_preview/<stem>.png and
trajectory.png; see `rvggt_jax.io.export.export_reconstruction`.

Failures exit non-zero with one line on stderr, `rvggt: error: ...` (set RVGGT_DEBUG=1
for the traceback). Compiled programs are cached across runs in $RVGGT_CACHE_DIR
(default ~/.cache/rvggt-jax/xla; RVGGT_CACHE_DIR=off disables it).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

PROG = "rvggt"
DEFAULT_CONF_THRESHOLD = "50%"
EXAMPLES_DIR = Path(__file__).resolve().parent / "examples_data"
DEMO_IMAGES = EXAMPLES_DIR / "images"
DEMO_WEIGHTS = EXAMPLES_DIR / "tiny"

RANDOM_WEIGHTS_NOTICE = (
    "NOTE: the demo runs a tiny VGGT with RANDOM weights (rvggt_jax/examples_data/tiny): it exercises "
    "the whole pipeline, the reconstruction itself is meaningless. For real results convert VGGT-1B "
    "(`rvggt convert`) and run `rvggt reconstruct --weights ...`."
)


class CLIError(Exception):
    """A failure reported as one line on stderr."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are one line too."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise CLIError(f"{message} (see `{self.prog} --help`)", code=2)


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------


def _one_line(msg: Any, limit: int = 400) -> str:
    """`msg` on one line, cut to about `limit` characters."""
    text = " ".join(str(msg).split())
    return text if len(text) <= limit else text[: limit - 3].rstrip() + "..."


def _write(text: str, file) -> None:
    """Print a line without tearing an active progress bar."""
    try:
        from tqdm.auto import tqdm

        tqdm.write(text, file=file)
        file.flush()
    except ImportError:  # pragma: no cover
        print(text, file=file, flush=True)


def _say(quiet: bool, *parts: Any) -> None:
    if not quiet:
        _write(" ".join(map(str, parts)), sys.stdout)


def _warn(msg: str) -> None:
    _write(f"{PROG}: warning: {_one_line(msg)}", sys.stderr)


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


def _available_memory_bytes() -> tuple[int | None, str]:
    """Memory of the default JAX device (accelerator limit, or host RAM for CPU)."""
    try:
        import jax

        dev = jax.devices()[0]
        stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
        if stats and stats.get("bytes_limit"):
            return int(stats["bytes_limit"]), f"{dev.platform.upper()} memory"
    except Exception:  # pragma: no cover - best effort
        pass
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "available host RAM"
    except OSError:
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "host RAM"
    except (ValueError, OSError, AttributeError):
        return None, "memory"


def estimate_memory_bytes(config: Any, frames: int, height: int, width: int, params: Any = None) -> int:
    """Rough peak memory (bytes) of one forward pass of `frames` images of `height x width`.

    float32: parameters + twice (scores and softmax) the largest attention score tensor
    + the token activations, the kept aggregator layers and the DPT heads'
    full-resolution maps. The score tensor of a global layer is [heads, queries,
    K/V slots]: from `rvggt_jax.cost_report` (which knows the compression preset's
    shapes) when available, else dense ([heads, S*P, S*P], P = 1 + registers + h*w
    tokens per frame); frame attention is [S, heads, P, P].
    """
    ps = config.patch_size
    p = config.patch_start_idx + (height // ps) * (width // ps)
    n = frames * p
    heads = config.num_heads
    f32 = 4
    score_elems = max(n * n, frames * p * p)
    try:
        import rvggt_jax

        report = rvggt_jax.cost_report(config, frames, height, width)
        score_elems = max(frames * p * p, *(
            r["queries"] * r["kv_slots"] * (frames if r["kind"] == "frame" else 1) for r in report["layers"]))
    except Exception:  # no cost model (or it cannot price this config): dense estimate
        pass
    scores = heads * score_elems * f32
    tokens = n * config.embed_dim * f32
    kept = len(config.needed_layers(False)) * n * 2 * config.embed_dim * f32
    heads_maps = 2 * frames * height * width * config.dpt_head.features * f32 * 4
    n_params = 0
    if params is not None:
        import jax

        n_params = sum(int(getattr(x, "size", 0)) for x in jax.tree_util.tree_leaves(params))
    return n_params * f32 + 2 * scores + 8 * tokens + kept + heads_maps


def _check_memory(config: Any, frames: int, height: int, width: int, params: Any) -> None:
    need = estimate_memory_bytes(config, frames, height, width, params)
    have, what = _available_memory_bytes()
    if have is not None and need > 0.9 * have:
        _warn(f"this run needs about {need / 2**30:.1f} GiB ({frames} frames of {width}x{height}) but "
              f"{what} is {have / 2**30:.1f} GiB: it will probably run out of memory; use fewer frames "
              f"(--max-frames) or a compression preset (--preset)")


# ---------------------------------------------------------------------------------------
# reconstruct
# ---------------------------------------------------------------------------------------


def _load_model(weights: Path, quiet: bool = True):
    """`(params, config)` of a checkpoint, without the track head (unused here)."""
    if not weights.exists():
        raise CLIError(f"checkpoint not found: {weights}")
    try:
        from rvggt_jax import load_pretrained

        return load_pretrained(str(weights), skip_track=True, progress=not quiet)
    except CLIError:
        raise
    except Exception as e:
        if type(e).__name__ == "CheckpointError":
            raise CLIError(f"checkpoint {weights} does not fit the model: {_one_line(e)}") from None
        raise CLIError(f"cannot load checkpoint {weights}: {_one_line(e)}") from None


def reconstruct(images_dir: str | Path, weights: str | Path, out_dir: str | Path, *, preset: str | None = None,
                mode: str = "crop", conf_threshold: str = DEFAULT_CONF_THRESHOLD, max_frames: int | None = None,
                points_from: str = "depth", max_points: int | None = 2_000_000, quiet: bool = False) -> dict:
    """Reconstruct the images of `images_dir` (sorted by name) and write every output
    to `out_dir`. Returns the export summary. Raises `CLIError` with a one-line message."""
    from tqdm.auto import tqdm

    from rvggt_jax.io.export import export_reconstruction, parse_threshold, sanitize_cameras
    from rvggt_jax.io.images import IMAGE_EXTENSIONS, ImageLoadError, find_images, load_images_with_info

    images_dir, weights, out_dir = Path(images_dir), Path(weights), Path(out_dir)
    # -- cheap checks first --------------------------------------------------------------
    if mode not in ("crop", "pad"):
        raise CLIError(f"unknown mode {mode!r}; use crop or pad")
    try:
        parse_threshold(conf_threshold)
    except ValueError as e:
        raise CLIError(str(e)) from None
    if max_frames is not None and max_frames < 1:
        raise CLIError(f"--max-frames must be at least 1; got {max_frames}")
    if preset is not None and preset not in known_presets():
        raise CLIError(f"unknown preset {preset!r}; known presets: {', '.join(known_presets())}")
    if max_points is not None and max_points < 1:
        raise CLIError(f"--max-points must be at least 1; got {max_points}")
    if out_dir.exists() and not out_dir.is_dir():
        raise CLIError(f"output path exists and is not a folder: {out_dir}")
    if points_from not in ("depth", "pointmap"):
        raise CLIError(f"unknown point source {points_from!r}; use depth or pointmap")
    try:
        paths, skipped = find_images(images_dir)
    except (FileNotFoundError, NotADirectoryError) as e:
        raise CLIError(str(e)) from None
    if not paths:
        if not skipped:
            raise CLIError(f"image folder is empty: {images_dir}")
        raise CLIError(f"no images in {images_dir} ({len(skipped)} other entries skipped; "
                       f"image files end in {', '.join(IMAGE_EXTENSIONS)})")
    if not weights.exists():
        raise CLIError(f"checkpoint not found: {weights}")
    if skipped and not quiet:
        _say(quiet, f"skipping {len(skipped)} non-image entr{'y' if len(skipped) == 1 else 'ies'} in {images_dir}")
    chosen = select_frames(paths, max_frames)
    if len(chosen) < len(paths):
        _say(quiet, f"using {len(chosen)} of {len(paths)} images (--max-frames {max_frames}, evenly spaced)")

    # -- images --------------------------------------------------------------------------
    with tqdm(total=len(chosen), desc="loading images", unit="img", disable=quiet, leave=False) as bar:
        def progress(it):
            for x in it:
                yield x
                bar.update(1)

        try:
            images, infos = load_images_with_info(chosen, mode=mode, progress=progress)
        except ImageLoadError as e:
            bar.close()
            raise CLIError(str(e)) from None
    s, _, h, w = images.shape
    _say(quiet, f"loaded {s} image{'s' * (s != 1)} -> network input {w}x{h} ({mode})")

    # -- model ---------------------------------------------------------------------------
    stages = ["loading weights", "checking memory", "running the model", "decoding cameras", "writing outputs"]
    t0 = time.perf_counter()
    with tqdm(total=len(stages), unit="step", disable=quiet, leave=False, desc=f"reconstruct ({stages[0]})",
              bar_format="{desc}: {n_fmt}/{total_fmt} [{elapsed}]") as bar:
        def stage(i):
            bar.set_description_str(f"reconstruct ({stages[i]})", refresh=False)
            if i:
                bar.update(1)
            else:
                bar.refresh()

        stage(0)
        params, config = _load_model(weights, quiet)
        if preset is not None:
            try:
                config = config.with_compression(preset)
            except ValueError as e:
                raise CLIError(_one_line(e)) from None
        if points_from == "pointmap" and not config.enable_point:
            raise CLIError(f"checkpoint {weights} has no point head; use --points depth")
        stage(1)
        _check_memory(config, s, h, w, params)
        stage(2)
        out = _run_model(params, images, config, weights)
        stage(3)
        extrinsic, intrinsic = _decode_cameras(out["pose_enc"], (h, w))
        extrinsic, intrinsic, fixes = sanitize_cameras(extrinsic, intrinsic, (h, w))
        for msg in fixes:
            _warn(msg)
        stage(4)
        meta = dict(weights=str(weights), preset=config.compression.name, mode=mode,
                    conf_threshold=str(conf_threshold), points_from=points_from)
        summary = export_reconstruction(
            out_dir, [p.name for p in chosen], images, infos, extrinsic, intrinsic,
            out["depth"], out["depth_conf"], out.get("world_points"), out.get("world_points_conf"),
            points_from=points_from, conf_threshold=conf_threshold, max_points=max_points, meta=meta)
        bar.update(1)
    summary["seconds"] = time.perf_counter() - t0
    if summary["points"] == 0:
        _warn(f"no point passed the confidence threshold {conf_threshold}; points.ply is empty "
              f"(lower --conf-threshold, e.g. '0%')")
    if summary.get("colmap_renamed"):
        _warn(f"COLMAP image names cannot contain spaces: {len(summary['colmap_renamed'])} name(s) written with "
              f"'_' in sparse/images.txt (e.g. {summary['colmap_renamed'][0][1]!r})")
    _say(quiet, f"wrote {out_dir}: {summary['frames']} cameras, {summary['points']} points "
                f"(confidence >= {summary['conf_threshold']:.4g}) in {summary['seconds']:.1f} s")
    return summary


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


def _run_model(params, images, config, weights: Path) -> dict:
    import jax
    import numpy as np

    from rvggt_jax import rvggt_forward

    try:
        from rvggt_jax.model import InputError
    except ImportError:  # pragma: no cover
        InputError = ValueError  # type: ignore[misc,assignment]
    needed = [k for k, on in (("pose_enc", config.enable_camera), ("depth", config.enable_depth)) if not on]
    if needed:
        raise CLIError(f"checkpoint {weights} has no {' / '.join(needed)} head; reconstruct needs the camera and depth heads")
    enable_compilation_cache()
    try:
        out = jax.jit(rvggt_forward)(params, images, config)
        keys = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")
        return {k: np.asarray(out[k])[0] for k in keys if k in out}
    except InputError as e:
        raise CLIError(f"checkpoint {weights} does not fit the model: {_one_line(e)}") from None


def _decode_cameras(pose_enc, hw):
    import numpy as np

    from rvggt_jax.geometry import pose_encoding_to_extri_intri

    e, k = pose_encoding_to_extri_intri(pose_enc[None], hw)
    return np.asarray(e)[0], np.asarray(k)[0]


# ---------------------------------------------------------------------------------------
# convert / demo
# ---------------------------------------------------------------------------------------


def _convert(argv: Sequence[str]) -> int:
    """`rvggt convert ...` = the converter's own command line (`python -m convert`)."""
    try:
        from convert.cli import main as entry

        return int(entry(list(argv), prog=f"{PROG} convert") or 0)
    except ImportError:
        pass
    try:
        import convert as convert_pkg
    except ImportError as e:
        raise CLIError(f"the converter is not installed ({_one_line(e)})") from None
    entry = getattr(convert_pkg, "main", None)
    if entry is None:
        raise CLIError("the converter has no command-line entry (convert.main)")
    return int(entry(list(argv)) or 0)


def demo(out_dir: str | Path = "rvggt_demo", preset: str | None = None, quiet: bool = False) -> dict:
    """Run `reconstruct` on the bundled images with the bundled random-weight model."""
    print(RANDOM_WEIGHTS_NOTICE, flush=True)
    if not DEMO_WEIGHTS.exists() or not DEMO_IMAGES.exists():
        raise CLIError(f"bundled demo data missing under {EXAMPLES_DIR} (broken install?)")
    summary = reconstruct(DEMO_IMAGES, DEMO_WEIGHTS, out_dir, preset=preset, quiet=quiet)
    _say(quiet, f"demo outputs in {out_dir} (random weights: meaningless geometry)")
    return summary


# ---------------------------------------------------------------------------------------
# argument parsing
# ---------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description="VGGT feed-forward 3D reconstruction in JAX.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    p = sub.add_parser("convert", help="convert an upstream VGGT checkpoint (.safetensors/.pt) to rvggt-jax",
                       add_help=False)
    p.add_argument("args", nargs=argparse.REMAINDER, help="SRC DST [converter options]; see `rvggt convert --help`")

    presets = ", ".join(known_presets())
    p = sub.add_parser("reconstruct", help="reconstruct a folder of images",
                       description="Reconstruct cameras, depth and a point cloud from the images of a folder "
                                   "(sorted by name; other files are skipped).")
    p.add_argument("images_dir", metavar="IMAGES_DIR", help="folder of images (png, jpg, ...)")
    p.add_argument("--weights", required=True, metavar="CKPT",
                   help="checkpoint: a folder with model.safetensors [+ config.json], a .safetensors file, "
                        "or a converted (Orbax) folder")
    p.add_argument("--out", required=True, metavar="OUT_DIR", help="output folder (created)")
    _common_options(p, presets)
    p.add_argument("--mode", default="crop", choices=("crop", "pad"),
                   help="crop: width 518, height centre-cropped to <= 518 (default); "
                        "pad: longest side 518, white-padded to square")
    p.add_argument("--conf-threshold", default=DEFAULT_CONF_THRESHOLD, metavar="X",
                   help="keep points whose confidence is >= X (VGGT confidences are >= 1), or, written "
                        "'P%%', at or above the P-th percentile of all confidences (default %(default)s; "
                        "'0%%' keeps every point)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="use at most N images, evenly spaced over the sorted list")
    p.add_argument("--points", default="depth", choices=("depth", "pointmap"),
                   help="point cloud from the depth maps unprojected with the predicted cameras "
                        "(default) or from the point-map head")
    p.add_argument("--max-points", type=int, default=2_000_000, metavar="N",
                   help="cap on the points written to points.ply (random subset; default %(default)s)")

    p = sub.add_parser("demo", help="run the pipeline on bundled images with a tiny RANDOM-weight model",
                       description=RANDOM_WEIGHTS_NOTICE)
    p.add_argument("--out", default="rvggt_demo", metavar="DIR", help="output folder (default %(default)s)")
    _common_options(p, presets)

    from rvggt_jax.eval.cli import add_eval_parser

    add_eval_parser(sub)
    return parser


def _common_options(p: argparse.ArgumentParser, presets: str) -> None:
    p.add_argument("--preset", default=None, metavar="NAME",
                   help=f"compression preset of the global attention ({presets}); default: the checkpoint's")
    p.add_argument("--quiet", action="store_true", help="no progress bars or messages (errors and warnings only)")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `rvggt` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] == "convert":
            return _convert(argv[1:])
        args = build_parser().parse_args(argv)
        if args.command is None:
            build_parser().print_help()
            return 2
        if args.command == "reconstruct":
            reconstruct(args.images_dir, args.weights, args.out, preset=args.preset, mode=args.mode,
                        conf_threshold=args.conf_threshold, max_frames=args.max_frames, points_from=args.points,
                        max_points=args.max_points, quiet=args.quiet)
        elif args.command == "demo":
            demo(args.out, preset=args.preset, quiet=args.quiet)
        elif args.command == "eval":
            from rvggt_jax.eval.cli import run_eval_command

            run_eval_command(args)
        return 0
    except CLIError as e:
        if os.environ.get("RVGGT_DEBUG"):
            raise
        print(f"{PROG}: error: {_one_line(e)}", file=sys.stderr, flush=True)
        return e.code
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print(f"{PROG}: error: out of memory (use fewer frames with --max-frames or a compression --preset)",
              file=sys.stderr)
        return 1
    except Exception as e:  # one line, no traceback, for anything unexpected
        if os.environ.get("RVGGT_DEBUG"):
            raise
        msg = _one_line(e)
        if "RESOURCE_EXHAUSTED" in msg or "out of memory" in msg.lower():
            msg = "out of memory (use fewer frames with --max-frames or a compression --preset): " + msg[:300]
        print(f"{PROG}: error: {type(e).__name__}: {msg} (set RVGGT_DEBUG=1 for the traceback)",
              file=sys.stderr, flush=True)
        return 1


if __name__ == "__main__":
    sys.exit(main())
