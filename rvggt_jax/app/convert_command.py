"""`rvggt convert SRC DST [--config config.json] [--no-track] [--quiet] [--overwrite]`

Converts an upstream VGGT checkpoint (a `.safetensors` file, or a folder holding
`model.safetensors`) to an Orbax checkpoint folder `DST` (`DST/params/` + `DST/config.json`)
readable by `rvggt_jax.load_pretrained` (`rvggt_jax.weights.pretrained`).

Errors are `PROG: error: <one line>` on stderr, details (e.g. every mismatched tensor)
indented under it; PROG is `rvggt` when run as `rvggt convert`.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path
from typing import Sequence

from rvggt_jax.weights.checkpoint import CONFIG_NAME, SAFETENSORS_NAME, CheckpointError, config_for_safetensors, save_orbax
from rvggt_jax.app.messages import CLIError, format_error


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are raised (and printed as one line by `main`)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise CLIError(f"{message} (see `{self.prog} --help`)", code=2)


def build_parser(prog: str = "rvggt convert") -> argparse.ArgumentParser:
    ap = _Parser(prog=prog, description=__doc__.split("\n\n")[1].replace("\n", " "))
    ap.add_argument("src", type=Path, help=f"upstream .safetensors file, or a folder holding {SAFETENSORS_NAME}")
    ap.add_argument("dst", type=Path, help="output folder (Orbax checkpoint in DST/params + DST/config.json)")
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help=f"VGGT config.json (default: {CONFIG_NAME} beside the weights if present, else VGGT-1B)",
    )
    ap.add_argument(
        "--no-track", action="store_true", help="drop the track head (the saved config gets enable_track=false)"
    )
    ap.add_argument("--overwrite", action="store_true", help="replace an existing checkpoint in DST")
    ap.add_argument("--quiet", "-q", action="store_true", help="no progress bar or messages")
    return ap


def _resolve_src(src: Path) -> Path:
    if src.is_dir():
        st = src / SAFETENSORS_NAME
        if not st.is_file():
            raise FileNotFoundError(f"{src} has no {SAFETENSORS_NAME}")
        return st
    if not src.is_file():
        raise FileNotFoundError(f"no such file or folder: {src}")
    if src.suffix in (".pt", ".pth", ".bin"):
        raise ValueError(f"{src}: PyTorch checkpoints are not read (no torch dependency); convert the "
                         f"{SAFETENSORS_NAME} of the same hub repo (facebook/VGGT-1B has one)")
    return src


def main(argv: Sequence[str] | None = None, prog: str = "rvggt convert", *,
         timings: dict | None = None) -> int:
    """CLI entry point; returns the exit status (0 ok, 1 bad checkpoint / paths).
    `timings`, if given, receives `convert_s` and `save_s`."""
    name = "rvggt" if prog.startswith("rvggt") else "convert"
    try:
        args = build_parser(prog).parse_args(argv)
    except CLIError as e:
        print(format_error(name, str(e)), file=sys.stderr)
        return e.code
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    try:
        st = _resolve_src(args.src)
        cfg_path = args.config if args.config is not None else st.parent / CONFIG_NAME
        if args.config is not None and not cfg_path.is_file():
            raise FileNotFoundError(f"no such config file: {cfg_path}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            config = config_for_safetensors(st, cfg_path if cfg_path.is_file() else None)
        for w in caught:
            print(f"{name}: warning: {w.message}", file=sys.stderr)
        say(f"config: {cfg_path if cfg_path.is_file() else 'inferred from the tensor shapes'}")
        if args.no_track and config.enable_track:
            config = dataclasses.replace(config, enable_track=False)
        dst_params = args.dst / "params"
        if dst_params.exists() and not args.overwrite:
            raise FileExistsError(f"{dst_params} already exists (use --overwrite)")

        import jax

        from rvggt_jax.weights.converter import load_safetensors

        # Leaves go to the host CPU as jax.Arrays as they are converted: Orbax then saves
        # them without another full host copy (numpy leaves would cost one).
        cpu = jax.devices("cpu")[0]
        t0 = time.perf_counter()
        params = load_safetensors(
            st, config, skip_track=args.no_track, progress=not args.quiet, leaf_fn=lambda x: jax.device_put(x, cpu)
        )
        t1 = time.perf_counter()
        say(f"converted {st} in {t1 - t0:.1f}s; writing Orbax checkpoint to {args.dst} ...")
        save_orbax(params, config, args.dst, overwrite=args.overwrite)
        t2 = time.perf_counter()
        say(f"done in {t2 - t1:.1f}s")
        if timings is not None:
            timings.update(convert_s=t1 - t0, save_s=t2 - t1)
    except (CheckpointError, FileNotFoundError, FileExistsError, ValueError) as e:
        print(format_error(name, str(e)), file=sys.stderr)
        return 1
    return 0
