"""Loading and saving VGGT parameters, local checkpoints only (a Hugging Face repo id is
resolved to one by `rvggt_jax.weights.hub`; `rvggt_jax.weights.pretrained.load_pretrained`
takes either).

- `load_checkpoint(path)` -> `(params, config)` from an upstream `model.safetensors`
  (a folder holding one, or the file itself; a `config.json` beside it is read, else
  the layout is inferred from the tensor shapes, see `config_for_safetensors`) or from an
  Orbax checkpoint folder written by `save_orbax`.
- `save_orbax(params, config, dst_dir)` writes `dst_dir/params/` (Orbax) and
  `dst_dir/config.json`.

The converter itself is `rvggt_jax.weights.converter` (imported lazily here, as is Orbax,
so importing this module stays cheap); its error classes live in
`rvggt_jax.weights.errors`, which imports nothing of this package. This module imports
neither `hub` nor `pretrained` (they import it): no import cycle.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import shutil
import warnings
from pathlib import Path
from typing import Any, Mapping

from rvggt_jax.config import VGGTConfig
# Defined with the converter (which raises them too); imported here for the loaders and
# re-exported, so `rvggt_jax.weights.checkpoint.CheckpointError` keeps working.
from rvggt_jax.weights.errors import CheckpointError, CheckpointFileError, unreadable_message  # noqa: F401
from rvggt_jax.weights.integrity import check_loaded, write_digests
from rvggt_jax.weights.orbax_meta import contradiction, quiet_closed_loop_stragglers, restore_error, stored_shapes

ORBAX_SUBDIR = "params"
CONFIG_NAME = "config.json"
SAFETENSORS_NAME = "model.safetensors"
# Orbax reads at most this many GB at a time: peak ~1.3x the checkpoint instead of ~2x.
_RESTORE_CONCURRENT_GB = 1


class ConfigInferredWarning(UserWarning):
    """No config.json beside a .safetensors: the layout was inferred from its shapes."""


def safetensors_shapes(path: str | Path) -> dict[str, tuple[int, ...]]:
    """{key: shape} from the header of a `.safetensors` file (no tensor is read).
    Raises `CheckpointFileError` naming the file when it is truncated or corrupt."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="numpy") as f:
            return {k: tuple(int(d) for d in f.get_slice(k).get_shape()) for k in f.keys()}
    except Exception as e:  # SafetensorError has no importable base class across versions
        raise CheckpointFileError(unreadable_message(path, e)) from None


def config_for_safetensors(st: str | Path, config_json: str | Path | None = None) -> VGGTConfig:
    """The config of an upstream `.safetensors`: from `config_json` (default: the
    `config.json` beside the file) when present, else inferred from the tensor shapes
    (`rvggt_jax.weights.infer.infer_config`). An inferred layout other than VGGT-1B's emits one
    `ConfigInferredWarning` naming the values the shapes do not fix."""
    st = Path(st)
    cj = Path(config_json) if config_json is not None else st.parent / CONFIG_NAME
    if cj.is_file():
        return VGGTConfig.from_json(cj)
    from rvggt_jax.weights.infer import infer_config

    try:
        config, assumed = infer_config(safetensors_shapes(st))
    except CheckpointFileError:
        raise
    except ValueError as e:
        raise CheckpointFileError(f"{st}: {e}") from None
    if assumed:
        warnings.warn(ConfigInferredWarning(
            f"no {CONFIG_NAME} beside {st}: layout inferred from its tensor shapes (embed_dim {config.embed_dim}, "
            f"depth {config.depth}); not fixed by the shapes and assumed: {', '.join(assumed)} "
            f"(put the model's {CONFIG_NAME} beside it if these differ)"), stacklevel=2)
    return config


# ---- Orbax ------------------------------------------------------------------------------------


def _config_for(params: Mapping[str, Any], config: VGGTConfig) -> VGGTConfig:
    """`config` with enable_track off when the params carry no track head (e.g. --no-track)."""
    if config.enable_track and "track_head" not in params:
        return dataclasses.replace(config, enable_track=False)
    return config


def _check_tree(flat_have: Mapping[tuple, tuple], flat_want: Mapping[tuple, tuple],
                config: VGGTConfig | None = None) -> None:
    """Raise one `CheckpointError` for every path missing from / unexpected in / of another
    shape in `flat_have` ({path tuple: shape}) than `flat_want`; with `config`, its first
    line says how config.json contradicts the tensors when it can (`contradiction`)."""
    missing = [(".".join(p), s) for p, s in flat_want.items() if p not in flat_have]
    unexpected = [".".join(p) for p in flat_have if p not in flat_want]
    mismatched = [(".".join(p), s, flat_want[p]) for p, s in flat_have.items() if p in flat_want and s != flat_want[p]]
    if missing or unexpected or mismatched:
        summary = contradiction(config, {".".join(p): s for p, s in flat_have.items()}) if config else None
        raise CheckpointError(missing=missing, unexpected=unexpected, mismatched=mismatched, summary=summary)


def save_orbax(params: Mapping[str, Any], config: VGGTConfig, dst_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Write `params` (our converted pytree, numpy or jax leaves) as an Orbax checkpoint in
    `dst_dir/params/` plus `dst_dir/config.json`; returns `dst_dir`.

    The tree is checked against `config` first (`CheckpointError` on any difference). A
    tree without `track_head` is saved with `enable_track=False` in config.json."""
    import orbax.checkpoint as ocp

    from rvggt_jax.weights.converter import expected_param_paths, flatten_params

    config = _config_for(params, config)
    have = {p: tuple(v.shape) for p, v in flatten_params(params).items()}
    _check_tree(have, expected_param_paths(config))

    dst = Path(dst_dir).absolute()
    target = dst / ORBAX_SUBDIR
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} already exists (pass overwrite=True / --overwrite to replace it)")
    if target.exists():  # overwrite (Orbax's own force=True is ~10x slower than this)
        shutil.rmtree(target)
    dst.mkdir(parents=True, exist_ok=True)
    # Synchronous (no async host copy of the whole tree) and without OCDBT, which buffers
    # ~0.7x the checkpoint in memory before committing (VGGT-1B: +0.2 GB instead of
    # +3.3 GB over the params, and half the time). numpy leaves still cost Orbax a copy
    # each; host-CPU jax.Array leaves do not (see rvggt_jax.app.convert_command).
    ckptr = ocp.Checkpointer(ocp.PyTreeCheckpointHandler(use_ocdbt=False))
    try:
        with _quiet_absl():
            ckptr.save(target, args=ocp.args.PyTreeSave(params))
    finally:
        ckptr.close()
    config.to_json(dst / CONFIG_NAME)
    write_digests(dst, flatten_params(params))  # verified by the first load (integrity.py)
    return dst


@contextlib.contextmanager
def _quiet_absl():
    """Orbax logs routine absl WARNINGs (e.g. 'Skipping merge of OCDBT checkpoints') on
    every non-OCDBT save; keep errors only while we call it."""
    logger = logging.getLogger("absl")
    level = logger.level
    logger.setLevel(max(level, logging.ERROR))
    try:
        yield
    finally:
        logger.setLevel(level)


def _is_orbax_dir(d: Path) -> bool:
    return (d / "_CHECKPOINT_METADATA").is_file() or (d / "_METADATA").is_file()


def _read_config(ckpt_dir: Path) -> VGGTConfig:
    """The config.json of the Orbax folder `ckpt_dir` (beside it, or inside it). Without
    one the layout is unknown: the folder is damaged (save_orbax always writes it)."""
    for c in (ckpt_dir.parent / CONFIG_NAME, ckpt_dir / CONFIG_NAME):
        if c.is_file():
            return VGGTConfig.from_json(c)
    raise CheckpointFileError(
        f"converted checkpoint {ckpt_dir.parent} has no {CONFIG_NAME} (expected {ckpt_dir.parent / CONFIG_NAME}): "
        f"the folder is incomplete or damaged; convert the checkpoint again (`rvggt convert`)")


def _load_orbax(ckpt_dir: Path, config: VGGTConfig, *, skip_track: bool, device_put: bool, verify: bool):
    """The params tree of the Orbax folder `ckpt_dir` for `config`: stored shapes checked
    first (one `CheckpointError`), then restored, then checked (finite, digests)."""
    import jax
    import numpy as np
    import orbax.checkpoint as ocp

    from rvggt_jax.weights.converter import expected_param_paths, flatten_params, unflatten_params

    want = expected_param_paths(config, skip_track=skip_track)
    stored = stored_shapes(ckpt_dir)
    if stored is not None:  # before restoring: Orbax's own mismatch errors run to 1,000+ lines
        if skip_track:
            stored = {p: s for p, s in stored.items() if p[0] != "track_head"}
        _check_tree(stored, want, config)
    if device_put:  # straight to the default device, at most ~1 GB in flight on the host
        sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        item = {p: jax.ShapeDtypeStruct(s, np.float32, sharding=sharding) for p, s in want.items()}
        args = {p: ocp.ArrayRestoreArgs(sharding=sharding, global_shape=s, dtype=np.float32) for p, s in want.items()}
    else:
        item = {p: jax.ShapeDtypeStruct(s, np.float32) for p, s in want.items()}
        args = {p: ocp.RestoreArgs(restore_type=np.ndarray, dtype=np.float32) for p in want}
    restore = ocp.args.PyTreeRestore(
        item=unflatten_params(item),
        restore_args=unflatten_params(args),
        # save_orbax keeps config.json consistent with the saved tree, so a tree with a
        # track head is exactly a config with enable_track
        partial_restore=skip_track and config.enable_track,
    )
    ckptr = ocp.Checkpointer(ocp.PyTreeCheckpointHandler(restore_concurrent_gb=_RESTORE_CONCURRENT_GB))
    quiet_closed_loop_stragglers()  # a failed restore's leftover reads would print thousands of tracebacks
    try:
        with _quiet_absl():
            params = ckptr.restore(ckpt_dir, args=restore)
    except Exception as e:  # noqa: BLE001 - tensorstore raises bare Exceptions: a chunk unreadable
        raise restore_error(ckpt_dir, e) from None
    finally:
        ckptr.close()
    flat = flatten_params(params)
    # numpy restores come back in the stored shape whatever was asked: check them all
    _check_tree({p: tuple(v.shape) for p, v in flat.items()}, want, config)
    check_loaded(flat, ckpt_dir.parent, ckpt_dir, verify=verify, complete=not (skip_track and config.enable_track))
    return params


def cast_params(params: Mapping[str, Any], param_dtype: Any, heads: tuple[str, ...] = ()) -> dict:
    """The tree with the aggregator's weights (patch embed, frame and global blocks,
    tokens) in `param_dtype`; the heads' weights stay float32, since the heads compute in
    float32 (upstream's autocast keeps them there), except the subtrees named in `heads`
    (the low-memory mode's `VGGTConfig.half_weight_heads`: stored in `param_dtype`, still
    computing in float32). Works on arrays and on `jax.ShapeDtypeStruct` leaves. float32
    returns the tree unchanged."""
    import jax
    import jax.numpy as jnp

    dt = jnp.dtype(param_dtype)
    if dt not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.bfloat16)):
        raise ValueError(f"param_dtype must be float32 or bfloat16; got {param_dtype!r}")
    if dt == jnp.float32 or "aggregator" not in params:
        return dict(params)

    def cast(leaf):
        if isinstance(leaf, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct(leaf.shape, dt, sharding=getattr(leaf, "sharding", None))
        return leaf.astype(dt)

    return {name: (jax.tree.map(cast, sub) if name == "aggregator" or name in heads else sub)
            for name, sub in params.items()}


def load_checkpoint(
    path: str | Path,
    *,
    skip_track: bool = False,
    device_put: bool = True,
    progress: bool = False,
    param_dtype: Any = "float32",
    verify: bool = False,
) -> tuple[dict, VGGTConfig]:
    """Load VGGT parameters from a local checkpoint -> `(params, config)`.

    `path` is one of:
      - a folder with `model.safetensors` (+ optional `config.json`, else the layout
        is inferred from the shapes, `config_for_safetensors`);
      - a `.safetensors` file (a `config.json` beside it is used if present);
      - an Orbax folder written by `save_orbax` (`params/` + `config.json`), or its
        `params/` subfolder.
    (`rvggt_jax.weights.pretrained.load_pretrained` also takes a Hugging Face repo id.)
    Upstream checkpoints are converted on the fly (checked first, one `CheckpointError`
    for every problem). `skip_track=True` drops the track head (and returns a config with
    `enable_track=False`). Leaves are float32 `jax.Array`s on the default device, or numpy
    arrays with `device_put=False`; `param_dtype="bfloat16"` stores the aggregator's
    weights in bfloat16 (half their memory; `cast_params`), for
    `config.with_dtype("bfloat16")`.

    Every array is checked finite as it is loaded (`NonFiniteWeightError` naming it), and
    an Orbax folder's arrays against the digests `save_orbax` recorded, once per copy or
    on every load with `verify=True` (`DigestMismatchError`; `rvggt_jax.weights.integrity`).
    A damaged Orbax folder (no config.json, an unreadable chunk) raises
    `CheckpointFileError` naming the file or parameter.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"checkpoint path does not exist: {p}")

    if p.is_file():
        if p.suffix != ".safetensors":
            raise ValueError(f"{p}: expected a .safetensors file or a checkpoint folder"
                             + (" (PyTorch .pt files are not read: use the repo's model.safetensors)"
                                if p.suffix in (".pt", ".pth", ".bin") else ""))
        st, config = p, config_for_safetensors(p)
    elif _is_orbax_dir(p / ORBAX_SUBDIR) or _is_orbax_dir(p):
        ckpt_dir = p / ORBAX_SUBDIR if _is_orbax_dir(p / ORBAX_SUBDIR) else p
        config = _read_config(ckpt_dir)
        params = _load_orbax(ckpt_dir.absolute(), config, skip_track=skip_track, device_put=device_put,
                             verify=verify)
        return cast_params(params, param_dtype), _final_config(config, skip_track)
    elif (p / SAFETENSORS_NAME).is_file():
        st, config = p / SAFETENSORS_NAME, config_for_safetensors(p / SAFETENSORS_NAME)
    else:
        raise FileNotFoundError(
            f"{p} holds neither an Orbax checkpoint written by save_orbax ({ORBAX_SUBDIR}/ + {CONFIG_NAME}) "
            f"nor an upstream {SAFETENSORS_NAME}"
        )

    from rvggt_jax.weights.converter import load_safetensors

    leaf_fn = None
    if device_put:
        import jax

        leaf_fn = jax.device_put
    params = load_safetensors(st, config, skip_track=skip_track, progress=progress, leaf_fn=leaf_fn)
    return cast_params(params, param_dtype), _final_config(config, skip_track)


def _final_config(config: VGGTConfig, skip_track: bool) -> VGGTConfig:
    return dataclasses.replace(config, enable_track=False) if skip_track and config.enable_track else config
