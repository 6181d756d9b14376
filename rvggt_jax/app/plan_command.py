"""`rvggt plan`: will a forward fit an accelerator? XLA's own plan of it, compiled here for
the target without the device (nothing runs, no weights needed).

    rvggt plan --frames 1000 --target h200 --preset regime --dtype bfloat16
    rvggt plan --frames 300 --height 392 --width 518 --target rtx4090 --dtype bfloat16
    rvggt plan --frames 1000 --target tpu-v6e --devices 4

Exit status: 0 when it fits, 3 when it does not (what would is printed), 2 for bad
arguments, 1 when the planning itself fails (e.g. the compilers are not installed).
`rvggt_jax.app.cli` registers the sub-command (`add_plan_parser`) and calls
`run_plan_command`.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os

__all__ = ["DOES_NOT_FIT", "add_plan_parser", "run_plan_command"]

DOES_NOT_FIT = 3  # exit status of a plan that does not fit
MARGIN = 0.95  # estimates aim at this share of the target's memory (they are about linear)
JAX_GPU_FRACTION = 0.75  # JAX's GPU client lets XLA use this share unless told otherwise


def add_plan_parser(sub) -> None:
    """Register `plan` on an argparse sub-parsers object (imports neither JAX nor the model)."""
    from rvggt_jax.app.options import known_presets
    from rvggt_jax.planning.targets import TARGETS

    p = sub.add_parser(
        "plan", help="will it fit? XLA's memory plan of a forward for an accelerator (compiled here, not run)",
        description="Compile the forward for a GPU or TPU that need not be here (XLA's own compilers run on this "
                    "machine; `pip install \"rvggt-jax[plan]\"`) and print its memory plan against the target's "
                    "memory. Exit status 0: it fits; 3: it does not (what would fit is printed); 2: bad arguments.")
    p.add_argument("--frames", type=int, required=True, metavar="N", help="frames in one forward")
    p.add_argument("--target", required=True, metavar="T", help=f"accelerator: {', '.join(TARGETS)}")
    p.add_argument("--height", type=int, default=392, metavar="H",
                   help="network input height, a multiple of 14 (default %(default)s: a 4:3 photo as `rvggt "
                        "reconstruct` crops it)")
    p.add_argument("--width", type=int, default=518, metavar="W", help="network input width (default %(default)s)")
    p.add_argument("--preset", default="dense", metavar="P",
                   help=f"compression preset ({', '.join(known_presets())}, or a preset file path.json; "
                        f"default %(default)s)")
    p.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"),
                   help="the aggregator's compute dtype (default %(default)s)")
    p.add_argument("--param-dtype", default=None, choices=("float32", "bfloat16"),
                   help="the aggregator's weight dtype (default: the compute dtype, as `rvggt reconstruct` loads it)")
    p.add_argument("--batch", type=int, default=1, metavar="B", help="sequences in one forward (default 1)")
    p.add_argument("--images", default="uint8", choices=("uint8", "float32"),
                   help="the images' dtype in the program: uint8 as `rvggt reconstruct` passes them (default), "
                        "float32 for images in [0, 1] from Python (4x the bytes)")
    p.add_argument("--devices", type=int, default=1, metavar="N",
                   help="split the frames over N devices of the target (the figures are per device; default 1)")
    p.add_argument("--attention", default="auto", metavar="KERNEL",
                   help="attention kernel (default auto: the target's; see docs/accelerators.md)")
    p.add_argument("--config", default=None, metavar="JSON",
                   help="a model config.json (default: VGGT-1B's layout)")
    p.add_argument("--verify", action="store_true",
                   help="when it does not fit, compile the suggested --max-frames too (a second compile)")


def use_host_compilers() -> None:
    """Deviceless compiles need no device client: JAX on the CPU unless the user chose
    (JAX_PLATFORMS), and libtpu quiet and shareable (it compiles only). Before JAX's
    backends start; `import rvggt_jax` never does this."""
    from rvggt_jax.ops.xla_cpu import use_cpu_backend

    use_cpu_backend()
    os.environ.setdefault("TPU_WORKER_HOSTNAMES", "localhost")
    os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")


def _fail(message: str, code: int = 2):
    from rvggt_jax.app.messages import CLIError

    raise CLIError(message, code=code)


def _config(args: argparse.Namespace):
    """The model config of the plan, checked: VGGT-1B's (or --config's) with --preset,
    --dtype and --attention; bad values exit 2 naming the choices."""
    from rvggt_jax.app.options import known_presets
    from rvggt_jax.config import VGGTConfig

    for name in ("frames", "batch", "devices"):
        if getattr(args, name) < 1:
            _fail(f"--{name} must be at least 1; got {getattr(args, name)}")
    from rvggt_jax.diagnostics.presets_io import is_preset_path

    if not is_preset_path(args.preset) and args.preset not in known_presets():
        _fail(f"unknown preset {args.preset!r}; known presets: {', '.join(known_presets())}, or a preset file "
              f"path.json")
    try:
        base = VGGTConfig.vggt_1b() if args.config is None else VGGTConfig.from_json(args.config)
    except (OSError, ValueError, TypeError) as e:
        _fail(f"cannot read --config {args.config}: {e}")
    base = dataclasses.replace(base, enable_track=False)  # no query points: the forward runs no tracker
    ps = base.patch_size
    for name in ("height", "width"):
        v = getattr(args, name)
        if v < ps or v % ps:
            _fail(f"--{name} must be a positive multiple of the patch size {ps}; got {v}")
    try:
        from rvggt_jax.diagnostics.presets_io import resolve_preset

        base = dataclasses.replace(base, compression=resolve_preset(args.preset, base.depth))
        return base.with_dtype(args.dtype).with_attention(args.attention)
    except ValueError as e:
        _fail(str(e))


def fmt_bytes(n: int | None) -> str:
    """Bytes in GiB (MiB, KiB for small programs)."""
    if n is None:
        return "n/a"
    for unit, size in (("GiB", 2 ** 30), ("MiB", 2 ** 20)):
        if abs(n) >= 0.1 * size:
            return f"{n / size:.2f} {unit}"
    return f"{n / 1024:.1f} KiB"


def param_bytes(config, param_dtype: str) -> int:
    """Bytes of the weights the forward holds (no track head), as `memory_report` plans them."""
    from rvggt_jax.planning.memory import abstract_params

    import jax

    return sum(a.size * a.dtype.itemsize for a in jax.tree.leaves(abstract_params(config, param_dtype=param_dtype)))


def _describe(rep, target, label: str) -> list[str]:
    """The plan's lines: what was planned, for what, and its parts."""
    per = f" (per device, {rep.devices} devices)" if rep.devices > 1 else ""
    lines = [f"{label}, {rep.batch} x {rep.frames} frames of {rep.height} x {rep.width} ({rep.image_dtype}), "
             f"preset {rep.preset}, {rep.dtype} (weights {rep.param_dtype})",
             f"  target       {target.name}: {target.title}, compiled for {target.described_by} "
             f"({rep.device_kind}){per}"]
    if target.note:
        lines.append(f"               {target.note}")
    lines.append(f"  attention    {rep.attention or 'n/a'}")
    if rep.exhausted:
        lines.append("  arguments, outputs, temporaries: n/a (XLA refused the program before assigning its buffers)")
    else:
        lines += [f"  arguments    {fmt_bytes(rep.argument_bytes)} (weights + images)",
                  f"  outputs      {fmt_bytes(rep.output_bytes)}",
                  f"  temporaries  {fmt_bytes(rep.temp_bytes)}"]
        if rep.alias_bytes:
            lines.append(f"  aliased      -{fmt_bytes(rep.alias_bytes)}")
    have = rep.memory_bytes
    share = f" ({rep.total_bytes / have:.0%})" if have else ""
    lines.append(f"  total        {fmt_bytes(rep.total_bytes)} of {fmt_bytes(have)}{share}: {rep.memory_what}")
    if rep.compiler_checked:
        lines.append("               (an upper bound: XLA:TPU counts more temporaries than it places at once, and "
                     "it compiled the program for this chip's HBM)")
    if rep.peak_bytes:
        lines.append(f"  peak         {fmt_bytes(rep.peak_bytes)} (XLA's heap simulation of the scheduled program)")
    lines.append(f"  (XLA's plan, compiled in {rep.compile_seconds:.1f} s; nothing ran)")
    return lines


def suggestions(rep, target, params: int) -> list[tuple[str, str]]:
    """(option, why) pairs that would make a plan that does not fit fit, cheapest first.
    Frames and devices are estimates: memory ~ weights + frames x (the rest per frame)."""
    have = rep.memory_bytes
    out = []
    if rep.dtype == "float32":
        out.append(("--dtype bfloat16", "upstream's mixed precision: about half the activations and weights"))
    elif rep.param_dtype == "float32":
        out.append(("--param-dtype bfloat16", f"the weights in bf16: {fmt_bytes(params // 2)} less"))
    if rep.preset == "dense":
        out.append(("--preset regime", "RegimeVGGT's compressed global attention"))
    budget = MARGIN * have - params  # for what grows with the frames (per device)
    if budget <= 0:
        out.append(("a larger target", f"the weights alone take {fmt_bytes(params)}"))
        return out
    rest = rep.total_bytes - params  # activations, images, outputs: about linear in the frames
    fit = int(rep.frames * budget / rest)
    if 1 <= fit < rep.frames:
        out.append((f"--max-frames {fit}", f"about {fmt_bytes(int(params + rest * fit / rep.frames))} at {fit} "
                                           "frames (memory grows about linearly with the frames)"))
    elif fit < 1:
        out.append(("smaller images or a larger target",
                    f"one frame needs about {fmt_bytes(int(params + rest / rep.frames))}"))
    if target.platform != "cpu":
        n = max(rep.devices + 1, math.ceil(rep.devices * rest / budget))
        if target.platform == "tpu":
            n = 1 << (n - 1).bit_length()  # a TPU slice has a power of two chips
        elif n > 8:
            n = 8 * math.ceil(n / 8)  # whole hosts of 8 GPUs
        each = params + rest * rep.devices / n
        out.append((f"--devices {n}", f"the frames split over {n} devices: about {fmt_bytes(int(each))} each"))
    return out


def memory_fraction_note(rep, target) -> str | None:
    """For a GPU plan that fits but needs more than JAX's default share of the card: the
    XLA_PYTHON_CLIENT_MEM_FRACTION to run with (None otherwise)."""
    if target.platform != "cuda" or not rep.fits or rep.total_bytes <= JAX_GPU_FRACTION * rep.memory_bytes:
        return None
    need = math.ceil(100 * rep.total_bytes / rep.memory_bytes) / 100
    return (f"note: JAX lets XLA use {JAX_GPU_FRACTION:.0%} of a GPU's memory unless told otherwise: run with "
            f"XLA_PYTHON_CLIENT_MEM_FRACTION={min(need + 0.02, 0.99):.2f} (or more)")


def _verify(args, config, rep, option: str) -> str:
    """Compile the suggested --max-frames: one line saying whether it fits."""
    from rvggt_jax.planning.memory import memory_report

    frames = int(option.split()[-1])
    check = memory_report(config, frames, args.height, args.width, batch=args.batch, param_dtype=rep.param_dtype,
                          target=args.target, devices=args.devices, image_dtype=args.images)
    verdict = "fits" if check.fits else "does not fit either: lower it further"
    return f"  checked: {frames} frames need {fmt_bytes(check.total_bytes)}: {verdict}"


def run_plan_command(args: argparse.Namespace) -> int:
    """Execute a parsed `rvggt plan`: print the plan; 0 when it fits, `DOES_NOT_FIT` when
    not. Bad arguments raise `CLIError` (exit 2), a missing compiler exits 1."""
    use_host_compilers()
    from rvggt_jax.planning.memory import memory_report
    from rvggt_jax.planning.targets import CompilerMissingError, UnknownTargetError, get_target

    try:
        target = get_target(args.target)
    except UnknownTargetError as e:
        _fail(str(e))
    config = _config(args)
    param_dtype = args.param_dtype or config.dtype
    label = "VGGT-1B" if args.config is None else f"the model of {args.config}"
    try:
        rep = memory_report(config, args.frames, args.height, args.width, batch=args.batch, param_dtype=param_dtype,
                            target=target, devices=args.devices, image_dtype=args.images)
    except CompilerMissingError as e:
        _fail(str(e), code=1)
    except ValueError as e:  # devices the target cannot have, sizes the model refuses
        _fail(str(e))
    print("\n".join(_describe(rep, target, label)), flush=True)
    if rep.fits is None:
        print(f"memory of {target.name} unknown here: nothing to hold the plan against", flush=True)
        return 0
    if rep.fits and rep.compiler_checked and rep.headroom_bytes < 0:
        print(f"FITS: XLA:TPU placed the program in the {fmt_bytes(rep.memory_bytes)} of HBM it compiled for.",
              flush=True)
        return 0
    if rep.fits:
        print(f"FITS: {fmt_bytes(rep.headroom_bytes)} to spare.", flush=True)
        note = memory_fraction_note(rep, target)
        if note:
            print(note, flush=True)
        return 0
    print(f"DOES NOT FIT: needs {fmt_bytes(rep.total_bytes)}, {target.name} has {fmt_bytes(rep.memory_bytes)} "
          f"(short by {fmt_bytes(-rep.headroom_bytes)}). What would fit (estimates, each alone):", flush=True)
    tips = suggestions(rep, target, param_bytes(config, param_dtype))
    width = max(len(o) for o, _ in tips)
    for option, why in tips:
        print(f"  {option.ljust(width)}  {why}", flush=True)
    frames_tip = next((o for o, _ in tips if o.startswith("--max-frames")), None)
    if args.verify and frames_tip:
        print(_verify(args, config, rep, frames_tip), flush=True)
    return DOES_NOT_FIT
