"""Compression presets as JSON files: what `rvggt calibrate` writes and `--preset
path.json` reads wherever `--preset NAME` is accepted.

    save_preset(compression_config, "mine.json")
    comp = load_preset("mine.json")            # == compression_config
    comp = resolve_preset("regime" | "mine.json", depth)

The file: {"format": "rvggt-compression-preset", "version": 1, "compression": {every
`CompressionConfig` field}, "note": optional text}. Loading checks the format, unknown
keys (named), the bands against the layers and, given `depth`, the model's depth.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

from rvggt_jax.compression.config import CompressionConfig, make_compression, PRESETS

FORMAT = "rvggt-compression-preset"
VERSION = 1
_TOP_KEYS = {"format", "version", "compression", "note"}
_LAYER_LISTS = ("cache_band_starts", "no_cache_layers", "merge_only_layers", "frame_layers", "dense_layers")


class PresetError(ValueError):
    """A preset file that cannot be used (the message names the file and the problem)."""


def preset_dict(comp: CompressionConfig) -> dict[str, Any]:
    """Every field of `comp` as JSON values (tuples as lists)."""
    return {f.name: _jsonable(getattr(comp, f.name)) for f in dataclasses.fields(comp)}


def _jsonable(v: Any) -> Any:
    return [_jsonable(x) for x in v] if isinstance(v, tuple) else v


def save_preset(compression_config: CompressionConfig, path: str | os.PathLike, note: str | None = None) -> Path:
    """Write `compression_config` to `path` (JSON; folders created). `load_preset` of the
    file gives an equal `CompressionConfig`. Returns the path."""
    if not isinstance(compression_config, CompressionConfig):
        raise TypeError(f"save_preset takes a CompressionConfig; got {type(compression_config).__name__}")
    check_bands(compression_config, str(path))
    path = Path(path)
    doc: dict[str, Any] = dict(format=FORMAT, version=VERSION, compression=preset_dict(compression_config))
    if note:
        doc["note"] = note
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def load_preset(path: str | os.PathLike, depth: int | None = None) -> CompressionConfig:
    """The `CompressionConfig` of a preset file written by `save_preset` (or by hand).

    `depth`: the model's global layers; a preset written for another depth is refused
    (its bands and layer lists index layers). Raises `PresetError` naming the file and
    the problem: missing, not JSON, not a preset, unknown keys, invalid values, bands
    that do not cover the layers."""
    p = Path(path)
    if not p.is_file():
        raise PresetError(f"preset file not found: {p}" + (" (it is a folder)" if p.is_dir() else ""))
    try:
        doc = json.loads(p.read_text())
    except UnicodeDecodeError:
        raise PresetError(f"preset file {p} is not text (a JSON preset was expected)") from None
    except json.JSONDecodeError as e:
        raise PresetError(f"preset file {p} is not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise PresetError(f"preset file {p} is not an rvggt compression preset (its \"format\" must be {FORMAT!r}; "
                          f"write one with `rvggt calibrate` or diagnostics.save_preset)")
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise PresetError(f"preset file {p}: unknown keys {unknown} (known: {sorted(_TOP_KEYS)})")
    if doc.get("version") != VERSION:
        raise PresetError(f"preset file {p}: version {doc.get('version')!r} is not supported (this reads {VERSION})")
    fields = doc.get("compression")
    if not isinstance(fields, dict):
        raise PresetError(f"preset file {p}: \"compression\" must be an object of CompressionConfig fields")
    if "depth" not in fields:
        raise PresetError(f"preset file {p}: \"compression\" has no \"depth\" (the number of global layers)")
    try:
        comp = CompressionConfig.from_dict(fields)
    except (TypeError, ValueError) as e:
        raise PresetError(f"preset file {p}: {e}") from None
    check_bands(comp, str(p))
    if depth is not None and comp.depth != depth:
        raise PresetError(f"preset file {p} is written for {comp.depth} global layers; the model has {depth}")
    return comp


def check_bands(comp: CompressionConfig, where: str) -> None:
    """Bands that cover the layers: 0 <= middle start <= deep start <= depth for
    `merge_bands` and `kv_bands` (beyond depth only when their field, `merge_ratio` or
    `kv_sigma`, is the same in every band), layer lists inside [0, depth). `PresetError` naming
    `where` and the field."""
    d = comp.depth
    if not isinstance(d, int) or d < 1:
        raise PresetError(f"{where}: depth must be a positive integer; got {d!r}")
    for name, field in (("merge_bands", "merge_ratio"), ("kv_bands", "kv_sigma")):
        b = getattr(comp, name)
        # past the last layer, a band start only matters when its field differs per band
        # (the built-in presets keep 24-layer bands of uniform fields at other depths)
        v = getattr(comp, field)
        per_band = isinstance(v, tuple) and len(v) == 3 and d != 3 and len(set(v)) > 1
        if not (isinstance(b, tuple) and len(b) == 2 and all(isinstance(x, int) for x in b)
                and 0 <= b[0] <= b[1] and (b[1] <= d or not per_band)):
            raise PresetError(f"{where}: {name} {_jsonable(b)!r} do not cover the {d} layers: they are two integers "
                              f"0 <= middle start <= deep start <= {d} (shallow = [0, middle), middle = "
                              f"[middle, deep), deep = [deep, {d}))")
    for name in _LAYER_LISTS:
        bad = [i for i in getattr(comp, name) if not (isinstance(i, int) and 0 <= i < d)]
        if bad:
            raise PresetError(f"{where}: {name} holds {bad}, outside the layers 0..{d - 1}")


def is_preset_path(value: str | os.PathLike) -> bool:
    """Whether a --preset value names a file (ends in .json or contains a path separator)
    rather than a built-in preset."""
    s = os.fspath(value)
    return s.lower().endswith(".json") or "/" in s or os.sep in s


def resolve_preset(value: str | os.PathLike, depth: int) -> CompressionConfig:
    """--preset NAME (a built-in preset for `depth` layers) or --preset path.json (a
    preset file, `load_preset`). `PresetError` for an unknown name or a bad file."""
    if is_preset_path(value):
        return load_preset(value, depth)
    if value not in PRESETS:
        raise PresetError(f"unknown preset {value!r}; known presets: {', '.join(PRESETS)}, or a preset file "
                          f"path.json")
    return make_compression(str(value), depth)
