"""The model side of the commands: load a checkpoint (a local path or a hub repo id),
keep compiled programs across runs, run the forward (on one device or a "frames" mesh),
each failure a one-line `CLIError` naming the checkpoint."""

from __future__ import annotations

import os
import threading
import warnings
from pathlib import Path

from rvggt_jax.app.console import say, warn
from rvggt_jax.app.messages import CLIError, one_line


def resolve_weights(weights: str | Path, quiet: bool) -> Path:
    """The local checkpoint of `weights`: a bundled model's folder ("rvggt-small",
    `rvggt_jax.weights.pretrained.BUNDLED`), a hub repo id downloaded and converted once
    (its progress said unless quiet), a local path as it is."""
    from rvggt_jax.weights.hub import HubError, resolve_checkpoint
    from rvggt_jax.weights.pretrained import BUNDLED, bundled_path

    if str(weights) in BUNDLED:
        try:
            return bundled_path(str(weights))
        except FileNotFoundError as e:
            raise CLIError(str(e)) from None
    try:
        return resolve_checkpoint(weights, progress=not quiet, say=lambda m: say(quiet, m))
    except HubError as e:
        raise CLIError(str(e)) from None


def trained_width(local_weights: str | Path) -> int | None:
    """The network size (its longer side) a checkpoint folder's config.json says it was
    trained at (`rvggt_jax.weights.pretrained.train_image_size`), or None."""
    from rvggt_jax.weights.pretrained import train_image_size

    size = train_image_size(local_weights)
    return max(size) if size else None


def load_model(weights: str | Path, quiet: bool = True, name: str | Path | None = None, with_track: bool = False):
    """`(params, config)` of a checkpoint (local path or hub repo id), without the
    track head unless `with_track` (`--ba` tracks with it); `name` is how messages call it
    (default: `weights`).
    Warnings of the loader become `rvggt: warning:` lines."""
    name = weights if name is None else name
    local = resolve_weights(weights, quiet)
    if not Path(local).exists():
        raise CLIError(f"checkpoint not found: {name}")
    try:
        from rvggt_jax.weights.checkpoint import load_checkpoint

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            loaded = load_checkpoint(str(local), skip_track=not with_track, progress=not quiet)
        for w in caught:
            if issubclass(w.category, UserWarning):
                warn(str(w.message))
        return loaded
    except Exception as e:
        from rvggt_jax.weights.errors import CheckpointError, CheckpointFileError

        if isinstance(e, CheckpointError):
            raise CLIError(f"checkpoint {name} does not fit the model: {e}") from None
        if isinstance(e, CheckpointFileError):  # unreadable, damaged, non-finite: the message names it
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
    from rvggt_jax.errors import InputError
    from rvggt_jax.app.pipeline import run_model as forward

    enable_compilation_cache()
    try:
        return interruptible(forward, params, images, config, compiled, mesh)
    except InputError as e:
        raise CLIError(f"checkpoint {weights} does not fit the model: {one_line(e)}") from None
    except ValueError as e:  # a head missing
        raise CLIError(f"checkpoint {weights}: {one_line(e)}") from None


# set when Ctrl-C left a forward running in its worker thread (`interruptible`)
ABANDONED_FORWARD = threading.Event()


def interruptible(fn, *args):
    """fn(*args) in a worker thread, the main thread waiting in 0.1 s slices: Python runs
    a Ctrl-C's handler only between bytecodes of the main thread, and a forward blocks
    inside XLA for minutes, so a direct call would hold KeyboardInterrupt back until it
    ends. The interrupted computation cannot be cancelled: `rvggt`'s main then leaves the
    process at once (`ABANDONED_FORWARD`) rather than wait for it at exit."""
    result: dict = {}

    def work():
        try:
            import jax

            result["value"] = jax.block_until_ready(fn(*args))
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            result["error"] = e

    worker = threading.Thread(target=work, name="rvggt-forward", daemon=True)
    worker.start()
    try:
        while worker.is_alive():
            worker.join(0.1)
    except KeyboardInterrupt:
        ABANDONED_FORWARD.set()
        raise
    if "error" in result:
        raise result["error"]
    return result["value"]


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


def model_for(local_weights, weights, options: ReconstructOptions):
    """`(params, config)` of the checkpoint with the options' preset, dtype and low-memory
    mode applied."""
    params, config = load_model(local_weights, options.quiet, name=weights, with_track=options.ba is not None)
    if options.preset is not None:
        import dataclasses

        from rvggt_jax.diagnostics.presets_io import resolve_preset

        try:
            config = dataclasses.replace(config, compression=resolve_preset(options.preset, config.depth))
        except ValueError as e:
            raise CLIError(one_line(e)) from None
    if options.points_from == "pointmap" and not config.enable_point:
        raise CLIError(f"checkpoint {weights} has no point head; use --points depth")
    if options.dtype != config.dtype or options.low_memory:
        from rvggt_jax.weights.checkpoint import cast_params

        config = config.with_dtype(options.dtype).with_low_memory(options.low_memory or config.low_memory)
        params = cast_params(params, options.dtype, heads=config.half_weight_heads)
    return params, config


def check_memory(config, shape: tuple[int, int, int], options: ReconstructOptions, image_dtype="float32"):
    """`(report, mesh)`: XLA's own plan of this forward for `shape` = (frames, height,
    width) (compiled, not run; the run uses the same compiled program), so that a forward
    that does not fit is refused before running rather than dying in the middle."""
    from rvggt_jax.planning.memory import InsufficientMemoryError, check_fits

    enable_compilation_cache()
    mesh = devices_mesh(options.devices)
    if not options.quiet and options.chunk_frames is None:  # one forward of every frame: its time, when long
        from rvggt_jax.planning.estimate import long_run_line

        line = long_run_line(config, *shape)
        if line:
            say(False, line)
    try:
        report = check_fits(config, *shape, param_dtype=options.dtype, mesh=mesh, image_dtype=image_dtype)
    except (InsufficientMemoryError, ValueError) as e:
        raise CLIError(str(e)) from None
    return report, mesh
