"""`rvggt finetune`: argument parsing only (the work is `rvggt_jax.train.loop.finetune`), so
that building the `rvggt` parser imports neither JAX nor optax."""

from __future__ import annotations

from pathlib import Path


def add_finetune_parser(sub) -> None:
    """The `rvggt finetune` subcommand."""
    p = sub.add_parser("finetune", help="fine-tune on scenes with cameras (+ depth): folder, CO3D, ScanNet, ...",
                       description="Fine-tune VGGT with optax (AdamW, warm-up + cosine, clipping) on the scenes of "
                                   "DATA_DIR in any format the evaluation reads (a folder of "
                                   "<scene>/{images/, cameras.json, depth/}, CO3D v2, ScanNet, 7 Scenes, NRGBD, DTU, "
                                   "COLMAP), a random frame count per step; see docs/training.md.")
    p.add_argument("data_dir", metavar="DATA_DIR")
    # (the names of rvggt_jax.train.data.TRAIN_FORMATS: building the parser imports no JAX)
    p.add_argument("--format", default="auto", dest="data_format",
                   choices=("auto", "folder", "co3d", "scannet", "7scenes", "nrgbd", "dtu", "colmap"),
                   help="DATA_DIR's layout (default: auto, the first format whose files are found, in this order)")
    p.add_argument("--require-depth", action="store_true",
                   help="a scene without depth maps is an error naming the file expected (default: camera loss only)")
    p.add_argument("--out", required=True, help="output folder (train state, log, fine-tuned model); resumes")
    p.add_argument("--weights", default=None, help="checkpoint to start from (folder, .safetensors or hub id)")
    p.add_argument("--config", default=None, help="config.json for a randomly initialised model (no --weights)")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--frames", default="2-24", metavar="N|MIN-MAX",
                   help="frames per scene: a count, or a range drawn at random every step (default %(default)s, "
                        "upstream's)")
    p.add_argument("--buckets", default=None, metavar="N,N,...",
                   help="the frame counts compiled (a drawn count is rounded down to one; default: the range's ends "
                        "and the powers of two between, 2,4,8,16,24)")
    p.add_argument("--size", default="224x294", help="network input HxW, multiples of 14 (default %(default)s)")
    p.add_argument("--batch", type=int, default=1, help="scenes per step (default %(default)s)")
    p.add_argument("--accumulate", type=int, default=1, metavar="K",
                   help="gradient accumulation: each step's --batch scenes in K micro-batches of batch/K, one at a "
                        "time (the memory of batch/K scenes, the update of all of them); K must divide --batch")
    p.add_argument("--devices", type=int, default=1, metavar="N",
                   help="train over N local devices (default %(default)s), split into the mesh axes \"data\" x "
                        "\"frames\": the --frames / F devices of a group on \"frames\" share each scene's frames "
                        "(the global attention around a ring, as `rvggt reconstruct --devices`), the N / "
                        "(--frames / F) groups on \"data\" take the batch's scenes (that count must divide "
                        "--batch / --accumulate)")
    p.add_argument("--frames-per-device", type=int, default=None, metavar="F",
                   help="frames of a scene on each device (it must divide --frames; default: all of them, i.e. "
                        "a \"frames\" axis of 1 and N devices on \"data\")")
    p.add_argument("--fsdp", action="store_true",
                   help="split the parameters and optimiser state over all N devices (FSDP) instead of a copy on "
                        "each: for models whose state does not fit one device (docs/training.md)")
    p.add_argument("--lr", type=float, default=1e-5, help="peak learning rate (default %(default)s)")
    p.add_argument("--warmup", type=int, default=None, help="warm-up steps (default: 10%% of --steps, <= 500)")
    p.add_argument("--train", default="all",
                   help="'all', 'heads', or comma-separated parameter path prefixes, e.g. depth_head,camera_head")
    p.add_argument("--preset", default=None, help="compression preset during training, a name or a preset file path.json "
                                                     "(default: dense)")
    p.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"))
    # (the names of rvggt_jax.config.REMAT_POLICIES: building the parser imports no JAX)
    p.add_argument("--remat", nargs="?", const="full", default="none", choices=("none", "layers", "full", "dots"),
                   help="rematerialisation (less memory, more time): --remat alone is 'full' (every aggregator "
                        "layer, the patch embed and the heads' frame groups recomputed in the backward pass); "
                        "'layers' the aggregator layers and DINO blocks only; 'dots' keeps their matmul outputs "
                        "(docs/training.md, \"Memory\"; default %(default)s)")
    p.add_argument("--save-every", type=int, default=500)
    p.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                   help="stop after this step (state saved; a rerun with the same --out continues exactly)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")


def run_finetune_command(args) -> int:
    """`rvggt finetune` from parsed arguments."""
    from rvggt_jax.errors import InputError
    from rvggt_jax.train.loop import FinetuneOptions, device_layout, finetune, load_model

    try:
        h, w = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must be HxW, e.g. 224x294; got {args.size!r}") from None
    try:
        lo, _, hi = args.frames.partition("-")
        frames = (int(lo), int(hi)) if hi else int(lo)
        buckets = tuple(int(b) for b in args.buckets.split(",") if b.strip()) if args.buckets else None
    except ValueError:
        raise InputError(f"--frames must be N or MIN-MAX and --buckets N,N,...; got {args.frames!r}, "
                         f"{args.buckets!r}") from None
    train = args.train if args.train in ("all", "heads") else tuple(t for t in args.train.split(",") if t)
    # a preset file is applied here (the train loop takes preset names)
    from rvggt_jax.diagnostics.presets_io import is_preset_path, load_preset, resolve_preset

    preset_file = args.preset if args.preset and is_preset_path(args.preset) else None
    if preset_file:
        load_preset(preset_file)  # a bad file fails before the model loads
    opts = FinetuneOptions(steps=args.steps, frames=frames, buckets=buckets, size=(h, w), batch=args.batch,
                           data_format=args.data_format, require_depth=args.require_depth, stop_at=args.stop_at,
                           accumulate=args.accumulate, devices=args.devices,
                           frames_per_device=args.frames_per_device, fsdp=args.fsdp,
                           learning_rate=args.lr, warmup_steps=args.warmup, train=train,
                           preset=None if preset_file else args.preset,
                           dtype=args.dtype, remat=args.remat, save_every=args.save_every, seed=args.seed)
    if not Path(args.data_dir).is_dir():
        raise InputError(f"no such data folder: {args.data_dir}")
    device_layout(opts)  # a layout that does not fit fails before the model loads
    params, config = load_model(args.weights, args.config, args.seed)
    if preset_file:
        import dataclasses

        config = dataclasses.replace(config, compression=resolve_preset(preset_file, config.depth))
    finetune(args.data_dir, args.out, params, config, opts, log=(lambda s: None) if args.quiet else print,
             progress=not args.quiet)
    return 0


def add_train_small_parser(sub) -> None:
    """The `rvggt train-small` subcommand."""
    p = sub.add_parser("train-small", help="train the small VGGT shipped as rvggt-small from scratch (procedural scenes)",
                       description="Train `VGGTConfig.rvggt_small()` from scratch on procedural scenes streamed from "
                                   "seeds (rvggt_jax.train.small): the recipe of the shipped model, fixed seed. "
                                   "Rerunning the same command resumes from OUT/state exactly. The shipped run took "
                                   "3200 steps on a 2-core CPU (rvggt_jax/examples_data/rvggt_small/README.md).")
    p.add_argument("--out", required=True, help="output folder (train state, log, OUT/model at the end); resumes")
    p.add_argument("--steps", type=int, default=None, help="total steps (default: the shipped recipe's)")
    p.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                   help="stop after this step (state saved; a rerun with the same --out continues exactly)")
    p.add_argument("--size", default=None, help="network input HxW, multiples of 14 (default: the recipe's 84x112)")
    p.add_argument("--frames", default=None, metavar="N|MIN-MAX",
                   help="frames per scene (default: the recipe's 2-8 in buckets 2,4,8)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save-every", type=int, default=None, help="checkpoint every N steps (default: the recipe's)")
    p.add_argument("--layer-scale", type=float, default=None, metavar="G",
                   help="start the frame, global and camera-trunk LayerScale at G (default: upstream's 0.01, the "
                        "shipped run's; from scratch they stay there: the model card)")
    p.add_argument("--ship", action="store_true",
                   help="when training is done, store OUT/model in the package as rvggt-small (float16 weights)")
    p.add_argument("--quiet", action="store_true")


def run_train_small_command(args) -> int:
    """`rvggt train-small` from parsed arguments."""
    import dataclasses

    from rvggt_jax.errors import InputError
    from rvggt_jax.train.data import frame_plan
    from rvggt_jax.train.small import SmallRecipe, ship, train_small

    changes: dict = {"seed": args.seed}
    if args.steps is not None:
        if args.steps < 1:
            raise InputError(f"--steps must be at least 1; got {args.steps}")
        changes["steps"] = args.steps
    if args.save_every is not None:
        if args.save_every < 1:
            raise InputError(f"--save-every must be at least 1; got {args.save_every}")
        changes["save_every"] = args.save_every
    if args.layer_scale is not None:
        if not args.layer_scale > 0:
            raise InputError(f"--layer-scale must be > 0; got {args.layer_scale}")
        changes["layer_scale"] = args.layer_scale
    if args.size is not None:
        try:
            changes["size"] = tuple(int(v) for v in args.size.lower().split("x"))
            assert len(changes["size"]) == 2
        except (ValueError, AssertionError):
            raise InputError(f"--size must be HxW, e.g. 84x112; got {args.size!r}") from None
    if args.frames is not None:
        try:
            lo, _, hi = args.frames.partition("-")
            rng = (int(lo), int(hi or lo))
        except ValueError:
            raise InputError(f"--frames must be N or MIN-MAX; got {args.frames!r}") from None
        changes["frames"], changes["buckets"] = rng, frame_plan(rng)[2]
    recipe = dataclasses.replace(SmallRecipe(), **changes)
    log = (lambda s: None) if args.quiet else print
    result = train_small(args.out, recipe, stop_at=args.stop_at, log=log, progress=not args.quiet)
    if args.ship:
        if not (result / "config.json").is_file():
            raise InputError(f"--ship needs a finished run: {args.out} stopped at {result.name} of {recipe.steps} steps")
        log(f"shipped as rvggt-small: {ship(result)}")
    return 0
