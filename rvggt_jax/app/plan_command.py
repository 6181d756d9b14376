"""`rvggt plan`: will a forward fit an accelerator? XLA's own plan of it, compiled here for
the target without the device (nothing runs, no weights needed).

    rvggt plan --frames 1000 --target h200 --preset regime --dtype bfloat16
    rvggt plan --frames 300 --height 392 --width 518 --target rtx4090 --dtype bfloat16
    rvggt plan --frames 1000 --target tpu-v6e --devices 4
    rvggt plan --frames 100 --target h100 --memory-gb 16 --dtype bfloat16   # a 16 GB card, H100's compiler
    rvggt plan --frames 1000 --target h100 --preset regime --dtype bfloat16 --param-dtype bfloat16 --low-memory

Exit status: 0 when it fits, 3 when it does not (alternatives are printed), 2 for bad
arguments, 1 when the planning itself fails (e.g. the compilers are not installed).
Besides the memory, the plan prints how long the forward is estimated to take on the
target (`planning.target_time`: the FLOPs at its peak and an assumed efficiency) and,
over several devices, what each sends around the ring per global layer.
Progress goes to stderr while XLA compiles (a TPU plan of VGGT-1B takes minutes); the
plan, one verdict and the alternatives to stdout. An alternative is "fits" only when it
was compiled ("planned") and fits; the others are estimates with their size (the
docstring of `alternatives` says which are compiled).
`rvggt_jax.app.cli` registers the sub-command (`add_plan_parser`) and calls
`run_plan_command`.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import sys
import threading
import time

from rvggt_jax.app.plan_verdict import fits, held_against, memory_fraction_note, planned_label, share, verdict
from rvggt_jax.planning.units import fmt_bytes

__all__ = ["DOES_NOT_FIT", "add_plan_parser", "run_plan_command"]

DOES_NOT_FIT = 3  # exit status of a plan that does not fit
MARGIN = 0.95  # estimates aim at this share of the target's memory (they are about linear)
PROGRESS_EVERY = 60.0  # seconds between "still compiling" lines: XLA says nothing for minutes


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
                        "float32 for images in [0, 1] from Python (4x the bytes). Either way the images are donated "
                        "to the program, as jax.jit(rvggt_forward, donate_argnums=1) does")
    p.add_argument("--devices", type=int, default=1, metavar="N",
                   help="split the frames over N devices of the target (the figures are per device; default 1)")
    p.add_argument("--attention", default="auto", metavar="KERNEL",
                   help="attention kernel (default auto: the target's; see docs/accelerators.md)")
    p.add_argument("--config", default=None, metavar="JSON",
                   help="a model config.json (default: VGGT-1B's layout)")
    p.add_argument("--low-memory", action="store_true",
                   help="the low-memory inference mode (VGGTConfig.with_low_memory: 16-bit outputs, the camera "
                        "head's weights in 16 bits with --param-dtype bfloat16, the DPT heads' coarse levels kept "
                        "reassembled; docs/memory_layout.md)")
    p.add_argument("--memory-gb", type=float, default=None, metavar="G",
                   help="hold the plan against G GiB per device instead of the target's own memory (a smaller "
                        "card planned with the target's compiler: --target h100 --memory-gb 16); the verdict and "
                        "the exit status follow G")
    p.add_argument("--check-suggestions", "--verify", dest="check_suggestions", action="store_true",
                   help="when it does not fit, compile the estimated alternatives (--frames N, --devices N) "
                        "too: one compile each, up to four (without it only the combined settings are compiled)")


def use_host_compilers() -> None:
    """Deviceless compiles need no device client: JAX on the CPU unless the user chose
    (JAX_PLATFORMS), and libtpu quiet and shareable (it compiles only). Before JAX's
    backends start; `import rvggt_jax` never does this."""
    from rvggt_jax.app.xla_cpu import use_cpu_backend

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
    gib = getattr(args, "memory_gb", None)
    if gib is not None and not (math.isfinite(gib) and gib > 0):
        _fail(f"--memory-gb must be a positive number of GiB; got {gib:g}")
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
        config = base.with_dtype(args.dtype).with_attention(args.attention)
        return config.with_low_memory() if getattr(args, "low_memory", False) else config
    except ValueError as e:
        _fail(str(e))


def param_bytes(config, param_dtype: str) -> int:
    """Bytes of the weights the forward holds (no track head), as `memory_report` plans them."""
    from rvggt_jax.planning.memory import abstract_params

    import jax

    return sum(a.size * a.dtype.itemsize for a in jax.tree.leaves(abstract_params(config, param_dtype=param_dtype)))


def _describe(rep, target, label: str) -> list[str]:
    """The plan's lines: what was planned, for what, and its parts."""
    per = f" (per device, {rep.devices} devices)" if rep.devices > 1 else ""
    mode = ", low-memory mode" if rep.low_memory else ""
    lines = [f"{label}, {rep.batch} x {rep.frames} frames of {rep.height} x {rep.width} ({rep.image_dtype}), "
             f"preset {rep.preset}, {rep.dtype} (weights {rep.param_dtype}){mode}",
             f"  target       {target.name}: {target.title}, compiled for {target.described_by} "
             f"({rep.device_kind}){per}"]
    if target.note:
        lines.append(f"               {target.note}")
    lines.append(f"  attention    {rep.attention or 'n/a'}")
    if rep.fallback:
        lines.append(f"  fallback     {rep.fallback}")
    if rep.exhausted:
        lines.append("  arguments, outputs, temporaries: n/a (XLA refused the program before assigning its buffers)")
    else:
        inputs = "weights + the part's inputs" if rep.parts else "weights + images"
        lines += [f"  arguments    {fmt_bytes(rep.argument_bytes)} ({inputs})",
                  f"  outputs      {fmt_bytes(rep.output_bytes)}",
                  f"  temporaries  {fmt_bytes(rep.temp_bytes)}"]
        if rep.alias_bytes:
            lines.append(f"  aliased      -{fmt_bytes(rep.alias_bytes)}"
                         + (" (outputs written into donated inputs' buffers)" if rep.parts else
                            " (outputs written into the donated images' buffer)" if rep.images_donated else ""))
    if rep.compiler_checked:
        # no share of the HBM here: this sum is not what the chip holds, and not the verdict
        lines.append(f"  total        {fmt_bytes(rep.total_bytes)}: the sum above, an upper bound, not the verdict "
                     "(XLA:TPU counts more temporaries than it places at once)")
    else:
        lines.append(f"  total        {fmt_bytes(rep.total_bytes)} of {fmt_bytes(rep.memory_bytes)}"
                     f"{share(rep.total_bytes, rep.memory_bytes)}: {rep.memory_what}")
    if rep.parts:
        lines.append("  parts        run one after another (the low-memory mode's forward in parts); the "
                     "figures above are the largest's: " + ", ".join(f"{n} {fmt_bytes(b)}" for n, b in rep.parts))
    if rep.peak_bytes:
        lines.append(f"  peak         {fmt_bytes(rep.peak_bytes)} (XLA's heap simulation of the scheduled program)")
    lines.append(f"  (XLA's plan, compiled in {rep.compile_seconds:.1f} s; nothing ran)")
    return lines


@dataclasses.dataclass
class Suggestion:
    """An alternative to a plan that does not fit. changes: `rvggt plan` arguments (parser
    dests) -> values, {} for advice that is no option (`advice` then says it); label:
    "planned, fits: ..." / "planned, does not fit: ..." (compiled) or "estimate: about ..."."""

    changes: dict
    label: str
    why: str = ""
    advice: str = ""

    @property
    def options(self) -> str:
        """The `rvggt plan` options of the alternative ("--dtype bfloat16 --frames 300")."""
        if not self.changes:
            return self.advice
        return " ".join(f"--{k.replace('_', '-')} {v}" for k, v in self.changes.items())

    @property
    def estimated(self) -> bool:
        return self.label.startswith("estimate")


def _estimate(size: float, have: int) -> str:
    return f"estimate: about {fmt_bytes(int(size))} of {fmt_bytes(have)}{share(size, have)}"


def setting_changes(args: argparse.Namespace) -> dict:
    """Every setting of `args` that saves memory, as `rvggt plan` arguments: bfloat16
    compute (its weights follow unless --param-dtype float32 keeps them), bfloat16
    weights, RegimeVGGT's compressed global attention."""
    changes = {}
    if args.dtype == "float32":
        changes["dtype"] = "bfloat16"  # upstream's mixed precision: about half the activations
    if args.param_dtype == "float32":
        changes["param_dtype"] = "bfloat16"
    if args.preset == "dense":
        changes["preset"] = "regime"
    return changes


def scaling(rep, target, params: int, base: dict) -> list[Suggestion]:
    """Fewer frames and more devices for `rep` (a plan with the settings `base`), estimated:
    memory ~ weights + frames x (the rest per frame), per device."""
    have = rep.memory_bytes
    budget = MARGIN * have - params  # for what grows with the frames (per device)
    if budget <= 0:
        return [Suggestion({}, "advice", f"the weights alone take {fmt_bytes(params)}", advice="a larger target")]
    out = []
    rest = rep.total_bytes - params  # activations, images, outputs: about linear in the frames
    fit = int(rep.frames * budget / rest)
    if 1 <= fit < rep.frames:
        out.append(Suggestion({**base, "frames": fit}, _estimate(params + rest * fit / rep.frames, have),
                              f"memory grows about linearly with the frames; `rvggt reconstruct` keeps {fit} "
                              f"frames with --max-frames {fit}"))
    elif fit < 1:
        out.append(Suggestion({}, "advice", f"one frame needs about {fmt_bytes(int(params + rest / rep.frames))}",
                              advice="smaller images or a larger target"))
    if target.platform != "cpu":
        n = max(rep.devices + 1, math.ceil(rep.devices * rest / budget))
        if target.platform == "tpu":
            n = 1 << (n - 1).bit_length()  # a TPU slice has a power of two chips
        elif n > 8:
            n = 8 * math.ceil(n / 8)  # whole hosts of 8 GPUs
        out.append(Suggestion({**base, "devices": n}, _estimate(params + rest * rep.devices / n, have),
                              f"the frames split over {n} devices (per device)"))
    return out


def _with(args: argparse.Namespace, changes: dict) -> argparse.Namespace:
    return argparse.Namespace(**{**vars(args), **changes})


def alternatives(args, rep, target, config, plan=None) -> list[Suggestion]:
    """What to change when `rep` does not fit. Every setting that saves memory combined
    (`setting_changes`) is compiled: one more compile, "planned". Fewer frames and more
    devices are estimated from the plan, and from the combined plan when that does not fit
    either; `args.check_suggestions` compiles each of those too (up to four compiles).
    plan: compiles (args, config, target, what) -> report (default `plan_once`)."""
    plan = plan or plan_once
    changes = setting_changes(args)
    tips, combined = [], None
    if changes:
        combined_config = _config(_with(args, changes))
        combined = plan(_with(args, changes), combined_config, target,
                        f"the alternative {Suggestion(changes, '').options}")
        tips.append(Suggestion(changes, planned_label(combined), "every setting that saves memory, combined"))
    tips += scaling(rep, target, param_bytes(config, rep.param_dtype), {})
    if combined is not None and not fits(combined):
        tips += scaling(combined, target, param_bytes(combined_config, combined.param_dtype), changes)
    if args.check_suggestions:
        for tip in tips:
            if tip.estimated and tip.changes:
                alt = _with(args, tip.changes)
                tip.label = planned_label(plan(alt, _config(alt), target, f"the alternative {tip.options}"))
    return tips


def say(line: str) -> None:
    """A progress line on stderr (stdout holds the plan)."""
    print(line, file=sys.stderr, flush=True)


def _elapsed(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    return f"{int(seconds // 60)} min {int(seconds % 60)} s"


@contextlib.contextmanager
def heartbeat(what: str, every: float | None = None):
    """A "still compiling" line every `every` seconds (PROGRESS_EVERY) while the body runs:
    XLA's compile prints nothing, for minutes on a TPU."""
    every = PROGRESS_EVERY if every is None else every
    done, t0 = threading.Event(), time.perf_counter()

    def beat():
        while not done.wait(every):
            say(f"  ... still compiling {what} ({_elapsed(time.perf_counter() - t0)})")

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def plan_once(args: argparse.Namespace, config, target, what: str):
    """`memory_report` of `config` for `args`' sizes on `target`, saying on stderr what
    compiles, how long it took, and every `PROGRESS_EVERY` s meanwhile. Bad values exit 2,
    a missing compiler 1."""
    from rvggt_jax.planning.memory import memory_report
    from rvggt_jax.planning.targets import CompilerMissingError

    slow = "; minutes for VGGT-1B" if target.platform == "tpu" else ""
    say(f"plan: tracing and compiling {what} for {target.name} ({target.described_by}; XLA, deviceless, nothing "
        f"runs{slow}) ...")
    t0 = time.perf_counter()
    try:
        with heartbeat(what):
            rep = memory_report(config, args.frames, args.height, args.width, batch=args.batch,
                                param_dtype=args.param_dtype or config.dtype, target=target, devices=args.devices,
                                image_dtype=args.images, progress=say)
    except CompilerMissingError as e:
        _fail(str(e), code=1)
    except ValueError as e:  # devices the target cannot have, sizes the model refuses
        _fail(str(e))
    done = "refused by XLA:TPU (more than its HBM)" if rep.exhausted else "compiled"
    say(f"  {done} in {_elapsed(time.perf_counter() - t0)}")
    return held_against(rep, getattr(args, "memory_gb", None))


def speed_lines(args: argparse.Namespace, config, target) -> list[str]:
    """The plan's time estimate and, over several devices, its ring lines
    (`planning.target_time`); an estimate that cannot be made is said, never fatal."""
    from rvggt_jax.planning.cost import ring_exchange
    from rvggt_jax.planning.target_time import ring_lines, time_estimate, time_line

    lines = []
    try:
        est = time_estimate(config, args.frames, args.height, args.width, target, batch=args.batch,
                            devices=args.devices)
        lines.append(time_line(est, target) if est is not None else
                     f"  time (estimate) n/a: the peak FLOP/s of {target.name} is not known here")
        if args.devices > 1 and target.platform == "cpu":
            lines.append(f"               ({args.devices} host devices share this CPU: split over them, the forward "
                         f"is no faster)")
    except Exception as e:  # noqa: BLE001 - an estimate is advice: it never stops a plan
        lines.append(f"  time (estimate) n/a: {type(e).__name__}: {e}")
    try:
        lines += ring_lines(ring_exchange(config, args.frames, args.height, args.width, args.devices, args.batch),
                            target, args.devices)
    except Exception as e:  # noqa: BLE001
        lines.append(f"  ring         n/a: {type(e).__name__}: {e}")
    return lines


def run_plan_command(args: argparse.Namespace) -> int:
    """Execute a parsed `rvggt plan`: print the plan and its verdict; 0 when it fits,
    `DOES_NOT_FIT` (with alternatives) when not. Bad arguments raise `CLIError` (exit 2),
    a missing compiler exits 1."""
    use_host_compilers()
    from rvggt_jax.planning.targets import CompilerMissingError, UnknownTargetError, get_target, target_devices

    try:
        target = get_target(args.target)
    except UnknownTargetError as e:
        _fail(str(e))
    config = _config(args)
    try:  # before any progress line: an error is then the only line (the devices are cached)
        target_devices(target, args.devices)
    except CompilerMissingError as e:
        _fail(str(e), code=1)
    except ValueError as e:  # devices the target cannot have
        _fail(str(e))
    label = "VGGT-1B" if args.config is None else f"the model of {args.config}"
    speed = speed_lines(args, config, target)  # (before the compile: seconds, where a TPU compile takes minutes)
    rep = plan_once(args, config, target, "the forward")
    print("\n".join(_describe(rep, target, label) + speed), flush=True)
    if fits(rep) is None:
        print(f"memory of {target.name} unknown here: nothing to hold the plan against", flush=True)
        return 0
    print(verdict(rep), flush=True)
    if fits(rep):
        note = memory_fraction_note(rep, target)
        if note:
            print(note, flush=True)
        return 0
    tips = alternatives(args, rep, target, config)
    estimates = ("" if args.check_suggestions else "; \"estimate\": not compiled, the weights plus a part linear "
                 "in the frames (--check-suggestions compiles them)")
    print(f"Alternatives (\"planned\": compiled here as this plan was{estimates}):", flush=True)
    width = max(len(t.options) for t in tips)
    for tip in tips:
        said = f"{tip.label}; {tip.why}" if tip.changes else tip.why
        print(f"  {tip.options.ljust(width)}  {said}", flush=True)
    return DOES_NOT_FIT
