"""`rvggt eval`: score compression presets on a dataset, or against dense.

    rvggt eval --dataset 7scenes --root /data/7scenes --weights W --presets dense,regime --stride 10 --out ev/
    rvggt eval --dataset images --root my_images/ --against dense --presets regime,fastvggt --out ev/
    rvggt eval --dataset tnt --root /tmp/syn --synthetic --presets dense,regime --size 70 --out ev/
    rvggt eval --dataset kitti --root /data/kitti/dataset --weights W --chunk-frames 60 --overlap 15 --out ev/

`rvggt_jax.app.cli` registers the sub-command (`add_eval_parser`) and calls `run_eval_command`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

__all__ = ["SequencePredictor", "add_eval_parser", "run_eval_command", "write_synthetic_set"]

SYNTHETIC_SCENES = 2
DEFAULT_WEIGHTS = "rvggt-small"
DEFAULT_WEIGHTS_NOTICE = (
    "NOTE: no --weights: rvggt eval runs rvggt-small, the small VGGT trained here on procedural scenes "
    "(rvggt_jax/examples_data/rvggt_small): its scores mean something on procedural scenes (--synthetic writes "
    "held-out ones), not on real data. For the paper's numbers pass --weights facebook/VGGT-1B; "
    "--weights tiny-random runs the random-weight test model.")


def add_eval_parser(sub) -> None:
    """Register `eval` on an argparse sub-parsers object."""
    from rvggt_jax.eval.datasets import FORMATS, SAMPLING

    p = sub.add_parser(
        "eval", help="score compression presets on a dataset (or against dense)",
        description="Run each preset on every scene of a dataset and score it with the dataset's protocol "
                    "(docs/eval.md), or, with --against dense, against the dense model's own outputs (no ground "
                    "truth needed). Writes OUT/results.csv, OUT/results.md, OUT/plots/ and per-scene results in "
                    "OUT/runs/ (a rerun with the same settings resumes from them).")
    p.add_argument("--dataset", required=True, choices=sorted(FORMATS), metavar="NAME",
                   help=f"dataset format: {', '.join(sorted(FORMATS))} ('images': a folder of images, for --against)")
    p.add_argument("--root", required=True, metavar="DIR", help="the dataset's folder")
    p.add_argument("--presets", default="dense,regime", metavar="P1,P2",
                   help="comma-separated compression presets (default %(default)s)")
    p.add_argument("--weights", default=None, metavar="CKPT",
                   help="checkpoint (default: rvggt-small, the bundled small model trained on procedural scenes; "
                        "tiny-random: the random-weight test model)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--frames", type=int, default=None, metavar="N",
                   help="at most N frames per scene (how: --sampling; default: the protocol's)")
    g.add_argument("--stride", type=int, default=None, metavar="K", help="every K-th frame (keyframes)")
    p.add_argument("--sampling", default=None, choices=SAMPLING,
                   help="how --frames picks frames (default: the protocol's, else first)")
    p.add_argument("--seed", type=int, default=0, help="seed of --sampling random (default 0)")
    p.add_argument("--scenes", default=None, metavar="S1,S2", help="comma-separated scene names (default: all)")
    p.add_argument("--size", type=int, default=None, metavar="W",
                   help="network image width, a multiple of 14 (default: the size the checkpoint was trained at "
                        "when its config.json records it, rvggt-small's 112; else 518, the paper's 518x392)")
    p.add_argument("--against", default=None, metavar="PRESET",
                   help="score each preset against this preset's outputs instead of ground truth (e.g. dense)")
    p.add_argument("--gt-root", default=None, metavar="DIR", help="ScanNet: folder of <scene>/<scene>_vh_clean_2.ply")
    p.add_argument("--synthetic", action="store_true",
                   help=f"first write {SYNTHETIC_SCENES} small procedural scenes with exact ground truth into --root, "
                        "in --dataset's format")
    q = p.add_argument_group("long sequences (--dataset kitti, tum)")
    q.add_argument("--chunk-frames", type=int, default=None, metavar="C",
                   help="predict each sequence in chunks of C frames, chained by Sim(3) on their shared frames "
                        "(default: one forward over all selected frames)")
    q.add_argument("--overlap", type=int, default=None, metavar="O",
                   help="frames shared by consecutive chunks (default: a quarter of --chunk-frames)")
    q.add_argument("--loop-closure", action="store_true",
                   help="close loops between chunks with a pose graph before scoring")
    p.add_argument("--no-plots", action="store_true", help="skip the plots")
    p.add_argument("--quiet", action="store_true", help="no progress bars or messages")


def write_synthetic_set(dataset: str, root: Path, scenes: int = SYNTHETIC_SCENES, frames: int | None = None,
                        size: int = 518) -> list[Path]:
    """`scenes` held-out procedural scenes (`rvggt_jax.synthetic.make_scene`, seeds 0, 1,
    ...) in `dataset`'s format under `root`, with the 7 Scenes calibration f = 525 x w / 640
    (which every format can store). Frames are w x h = 112 x 84 when the network size is
    112 or more (rvggt-small's own size), else size x 3/4 size: a numpy ray caster
    renders them, so larger networks get them upsampled.
    frames: per scene; default 21 where the protocol keeps every 10th frame (3 kept),
    else 8."""
    from rvggt_jax.eval.protocols import PROTOCOLS
    from rvggt_jax.synthetic import make_scene, write_scene

    if frames is None:
        p = PROTOCOLS.get(dataset)
        frames = 2 * p.stride + 1 if p is not None and p.stride > 1 else 8

    w = min(int(size), 112)
    h = w * 3 // 4
    return [write_scene(make_scene(frames, h, w, seed=i, focal=(525 * w / 640, 525 * h / 480),
                                   name=f"synthetic_{i + 1:03d}"), dataset, root) for i in range(scenes)]


class SequencePredictor:
    """`evaluate`'s predictor for chunked runs: (preset, image_paths, scene=) -> ({"extrinsics"
    [S, 3, 4], "intrinsics" [S, 3, 3]}, cost) through
    `rvggt_jax.app.long_sequence.predict_sequence`. time_s includes compilation (each
    chunk shape compiles once); compile_s and mem_gb are not measured (None)."""

    def __init__(self, weights: str, *, chunk_frames: int, overlap: int, loop_closure: bool = False,
                 size: int = 518, quiet: bool = True):
        import rvggt_jax

        self.params, self.config = rvggt_jax.load_pretrained(weights, skip_track=True)
        self.options = dict(chunk_frames=chunk_frames, overlap=overlap, loop_closure=loop_closure, mode="crop",
                            cache_dir=None, quiet=quiet, size=size)

    def __call__(self, preset: str, image_paths, scene=None, **_) -> tuple[dict, dict]:
        import numpy as np

        from rvggt_jax.app import long_sequence  # looked up per call: tests replace predict_sequence

        paths = [Path(p) for p in image_paths]
        t0 = time.perf_counter()
        traj = long_sequence.predict_sequence(paths, self.params, self.config.with_compression(preset), **self.options)
        elapsed = time.perf_counter() - t0
        ext = np.asarray(traj.extrinsics, np.float64)
        if ext.shape != (len(paths), 3, 4):
            raise ValueError(f"the chunked prediction gave extrinsics of shape {list(ext.shape)} for "
                             f"{len(paths)} images")
        return (dict(extrinsics=ext, intrinsics=np.asarray(traj.intrinsics, np.float64)),
                dict(time_s=elapsed, compile_s=None, mem_gb=None))


def _sequence_options(args: argparse.Namespace) -> dict:
    """The chunking settings of `args` checked: {} for a one-forward run, else
    chunk_frames / overlap / loop_closure; CLIError (one line) otherwise."""
    from rvggt_jax.eval.protocols import PROTOCOLS, SEQUENCE_DATASETS

    given = [flag for flag, v in (("--chunk-frames", args.chunk_frames), ("--overlap", args.overlap),
                                  ("--loop-closure", args.loop_closure)) if v not in (None, False)]
    if not given:
        return {}
    proto = PROTOCOLS.get(args.dataset)
    if proto is None or not proto.sequence:
        _fail(f"{given[0]} applies to the sequence datasets ({', '.join(SEQUENCE_DATASETS)}) only, not "
              f"--dataset {args.dataset}")
    if args.chunk_frames is None:
        _fail(f"{given[0]} needs --chunk-frames")
    if args.against:
        _fail("--chunk-frames scores against the ground truth: drop --against")
    c = args.chunk_frames
    o = max(1, c // 4) if args.overlap is None else args.overlap
    if c < 2:
        _fail(f"--chunk-frames must be at least 2; got {c}")
    if not 1 <= o < c:
        _fail(f"--overlap must be at least 1 (chunks are aligned on shared frames) and less than --chunk-frames "
              f"({c}); got {o}")
    return dict(chunk_frames=c, overlap=o, loop_closure=bool(args.loop_closure))


def _check_extras(args: argparse.Namespace) -> None:
    """The eval extra's packages, checked before any scene runs (a missing matplotlib used
    to surface after every scene had run): scipy (nearest neighbours), evo (trajectory
    errors), matplotlib (the plots, unless --no-plots)."""
    import importlib.util

    need = ["scipy", "evo"] + ([] if args.no_plots else ["matplotlib"])
    missing = [m for m in need if importlib.util.find_spec(m) is None]
    if missing:
        plots = " (or --no-plots, for matplotlib)" if "matplotlib" in missing else ""
        _fail(f"rvggt eval needs {', '.join(missing)}: pip install \"rvggt-jax[eval]\"{plots}")


def _fail(msg: str):
    from rvggt_jax.app.messages import CLIError

    raise CLIError(msg)


def run_eval_command(args: argparse.Namespace) -> list[dict]:
    """Execute a parsed `rvggt eval`; raises `rvggt_jax.app.messages.CLIError` on bad input."""
    from rvggt_jax.app.messages import one_line as _one_line
    from rvggt_jax.app.model_runner import enable_compilation_cache, resolve_weights, trained_width
    from rvggt_jax.weights.pretrained import BUNDLED
    from rvggt_jax.app.options import known_presets
    from rvggt_jax.eval.datasets import DatasetError
    from rvggt_jax.eval.protocols import AGAINST_HIGHER, AGAINST_METRICS, PROTOCOLS
    from rvggt_jax.eval.report import write_csv, write_markdown, write_plots
    from rvggt_jax.eval.runner import EvalSettings, Predictor, evaluate

    say = (lambda *_: None) if args.quiet else (lambda m: print(m, flush=True))
    presets = tuple(p.strip() for p in args.presets.split(",") if p.strip())
    if not presets:
        _fail("--presets is empty")
    for p in presets + ((args.against,) if args.against else ()):
        if p not in known_presets():
            _fail(f"unknown preset {p!r}; known presets: {', '.join(known_presets())}")
    if args.frames is not None and args.frames < 1:
        _fail(f"--frames must be at least 1; got {args.frames}")
    if args.stride is not None and args.stride < 1:
        _fail(f"--stride must be at least 1; got {args.stride}")
    if args.size is not None and (args.size < 14 or args.size % 14):
        _fail(f"--size must be a positive multiple of 14; got {args.size}")
    chunking = _sequence_options(args)
    _check_extras(args)
    if args.dataset == "images" and not args.against:
        _fail("--dataset images has no ground truth: add --against dense")
    weights = args.weights
    if weights is None:
        say(DEFAULT_WEIGHTS_NOTICE)
        weights = DEFAULT_WEIGHTS
    if weights in BUNDLED:
        weights = str(resolve_weights(weights, args.quiet))
    elif not Path(weights).exists():
        _fail(f"checkpoint not found: {weights}")
    size = args.size or trained_width(weights) or 518
    root = Path(args.root)
    if args.synthetic:
        root.mkdir(parents=True, exist_ok=True)
        made = write_synthetic_set(args.dataset, root, size=size)
        say(f"wrote {len(made)} synthetic scene(s) in {args.dataset} format under {root}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        _fail(f"output path exists and is not a folder: {out}")
    out.mkdir(parents=True, exist_ok=True)
    settings = EvalSettings(
        dataset=args.dataset, root=str(root), presets=presets, out=str(out), weights=str(weights), frames=args.frames,
        stride=args.stride, sampling=args.sampling, seed=args.seed,
        scenes=tuple(s.strip() for s in args.scenes.split(",")) if args.scenes else None, size=size,
        against=args.against, gt_root=args.gt_root, **chunking)
    enable_compilation_cache()
    factory = Predictor
    if chunking:
        def factory(w):
            return SequencePredictor(w, size=size, quiet=args.quiet, **chunking)
    t0 = time.perf_counter()
    try:
        rows = evaluate(settings, progress=not args.quiet, say=say, predictor_factory=factory)
    except (DatasetError, ValueError, FileNotFoundError) as e:
        _fail(_one_line(e))
    if not rows:
        _fail("nothing was evaluated (no scene, or every preset is the --against reference)")
    if args.against:
        metrics, higher, title = AGAINST_METRICS, AGAINST_HIGHER, f"{args.dataset}: presets against {args.against}"
    else:
        proto = PROTOCOLS[args.dataset]
        metrics, higher, title = proto.metrics, proto.higher_is_better, f"{args.dataset} ({proto.source})"
    write_csv(out / "results.csv", rows)
    write_markdown(out / "results.md", rows, metrics, title, higher)
    if not args.no_plots:
        write_plots(out / "plots", rows, metrics, out / "runs", args.against)
    say(f"evaluated {len({r['scene'] for r in rows})} scene(s) x {len({r['preset'] for r in rows})} preset(s) in "
        f"{time.perf_counter() - t0:.1f} s: {out / 'results.md'}, {out / 'results.csv'}")
    if not args.quiet:
        print((out / "results.md").read_text(), flush=True)
    return rows
