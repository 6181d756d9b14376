"""`rvggt analyze` and `rvggt calibrate`: the paper's diagnostics on your model and data
(`rvggt_jax.diagnostics`; docs/diagnostics.md says how to read what they write).

    rvggt analyze IMAGES --weights W --out DIR [--preset regime|path.json] [--m 256]
    rvggt calibrate SCENE... --weights W --out DIR      (SCENE: a folder of images)
    rvggt calibrate DIR/diagnostics.json... --out DIR   (what analyze wrote; no weights)

analyze writes rank_profile.png (layer x r95/m, the preset's bands shaded),
saliency.png (Psi and the protected patches), kv_t<T>k<K>.png (kept K/V per frame and
their union, one per K/V tile of the preset), groups_<band>.png (the merged groups of each
merge band) and diagnostics.json (every number). calibrate writes preset.json (a preset
file for --preset), calibration.json and rank_profile.png with the proposed bands.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from rvggt_jax.app.console import say, warn
from rvggt_jax.app.messages import CLIError, one_line

ANALYSIS_JSON = "diagnostics.json"
PRESET_JSON = "preset.json"
CALIBRATION_JSON = "calibration.json"
# widest --size: about twice reconstruct's 518 (5,329 patches a frame; the images are
# resized keeping their aspect and are at most as tall as wide). Unbounded, --size 1000006
# aborted the whole process in XLA (a failed size check in C++, no Python error).
MAX_SIZE = 1022
RANDOM_NOTE = ("random weights (the bundled tiny model): the numbers are well formed but mean nothing about "
               "any trained VGGT")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created; must be empty unless "
                                                               "--overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier rvggt run in DIR")
    p.add_argument("--m", type=int, default=256, metavar="M",
                   help="sampled query rows per layer and head (the paper's m; default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled query rows (default %(default)s)")
    p.add_argument("--max-frames", type=int, default=32, metavar="N",
                   help="at most N images per scene, evenly spaced (the paper: 32; default %(default)s)")
    p.add_argument("--size", type=int, default=None, metavar="W",
                   help=f"network input width in pixels, a multiple of 14 up to {MAX_SIZE} (default: 518, as "
                        "reconstruct; smaller is faster)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")


def add_diagnostics_parsers(sub) -> None:
    """The `analyze` and `calibrate` subcommands."""
    p = sub.add_parser("analyze", help="attention rank per layer, saliency and K/V coverage maps of a scene",
                       description="Measure the paper's diagnostics on a folder of images: the normalised "
                                   "attention rank r95/m of every global layer and head (dense model), the "
                                   "DINOv2 [CLS] saliency Psi and protected patches, the K/V positions kept "
                                   "under a preset and their union over frames, and the merged groups of each "
                                   "merge band. See docs/diagnostics.md.")
    p.add_argument("images_dir", metavar="IMAGES", help="folder of images (sorted by name)")
    p.add_argument("--weights", required=True, metavar="CKPT", help="checkpoint (as for reconstruct)")
    p.add_argument("--preset", default="regime", metavar="NAME|FILE",
                   help="compression preset whose bands, K/V grid and merges are shown: a name or a preset "
                        "file path.json (default %(default)s)")
    _common(p)

    p = sub.add_parser("calibrate", help="fit band boundaries, merge ratios and K/V rates to your model and data",
                       description="From the rank profiles of a few scenes (folders of images, measured with "
                                   "--weights, or the diagnostics.json files `rvggt analyze` wrote), propose a "
                                   "U-shaped band schedule by a stated rule (docs/diagnostics.md) and write it "
                                   "as a preset file for --preset path.json, with the cost model's predicted "
                                   "speedup against regime.")
    p.add_argument("inputs", nargs="+", metavar="SCENE",
                   help="folders of images, or diagnostics.json files written by `rvggt analyze`")
    p.add_argument("--weights", default=None, metavar="CKPT", help="checkpoint (needed for folders of images)")
    p.add_argument("--name", default="calibrated", help="name of the proposed preset (default %(default)s)")
    _common(p)


# ---------------------------------------------------------------------------------------
# shared steps
# ---------------------------------------------------------------------------------------


def _check_common(args) -> None:
    if args.m < 1:
        raise CLIError(f"--m must be at least 1; got {args.m}")
    if args.max_frames is not None and args.max_frames < 1:
        raise CLIError(f"--max-frames must be at least 1; got {args.max_frames}")
    if args.size is not None and (args.size < 14 or args.size % 14 or args.size > MAX_SIZE):
        raise CLIError(f"--size must be a positive multiple of 14 (the patch size) of at most {MAX_SIZE}; "
                       f"got {args.size}")


def _prepare(out: Path, args) -> None:
    from rvggt_jax.app.outdir import OutputDirError, prepare_output

    try:
        prepare_output(out, args.overwrite)
    except OutputDirError as e:
        raise CLIError(str(e)) from None


def _load_scene(folder: Path, args) -> tuple[np.ndarray, list[str]]:
    """images [S, 3, H, W] of a folder (at most --max-frames, --size wide) and their names."""
    from rvggt_jax.app.options import select_frames
    from rvggt_jax.io.images import TARGET_SIZE, ImageLoadError, find_images, load_images_with_info

    try:
        paths, _ = find_images(folder)
    except (FileNotFoundError, NotADirectoryError) as e:
        raise CLIError(str(e)) from None
    if not paths:
        raise CLIError(f"no images in {folder}")
    paths = select_frames(paths, args.max_frames)
    target = TARGET_SIZE
    if args.size is None and getattr(args, "weights", None) is not None:
        # a checkpoint trained at another size (rvggt-small: 112) is measured at that size
        from rvggt_jax.app.model_runner import resolve_weights, trained_width

        target = trained_width(resolve_weights(args.weights, True)) or TARGET_SIZE
    try:
        images, _ = load_images_with_info(paths, target=target)
    except ImageLoadError as e:
        raise CLIError(str(e)) from None
    if args.size is not None and args.size != images.shape[-1]:
        import jax

        s, _, h, w = images.shape
        nh = max(14, int(round(h * args.size / w / 14)) * 14)
        images = np.asarray(jax.image.resize(images, (s, 3, nh, args.size), "linear", antialias=True))
        images = np.clip(images, 0.0, 1.0)
    return images.astype(np.float32), [p.name for p in paths]


def _model(weights, quiet: bool):
    from rvggt_jax.app.model_runner import load_model, resolve_weights

    if weights is None:
        raise CLIError("--weights is needed to measure a folder of images")
    return load_model(resolve_weights(weights, quiet), quiet, name=weights)


def _preset(value: str, depth: int):
    from rvggt_jax.diagnostics import PresetError, resolve_preset

    try:
        return resolve_preset(value, depth)
    except PresetError as e:
        raise CLIError(str(e)) from None


def _is_random(config, weights) -> bool:
    """Whether `weights` is the bundled random-weight model (its numbers mean nothing)."""
    from rvggt_jax.app.commands import TINY_WEIGHTS

    if str(weights) == "tiny-random":
        return True
    try:
        return Path(weights).resolve() == TINY_WEIGHTS.resolve()
    except (OSError, TypeError):
        return False


def _floats(a) -> Any:
    """numpy -> JSON lists of floats / ints (rounded to 6 significant digits)."""
    a = np.asarray(a)
    if a.dtype.kind in "iub":
        return a.astype(int).tolist()
    return np.vectorize(lambda v: float(f"{v:.6g}"), otypes=[float])(a).tolist() if a.size else a.tolist()


# ---------------------------------------------------------------------------------------
# analyze
# ---------------------------------------------------------------------------------------


def preset_forward_layers(comp, geom) -> tuple[int, ...]:
    """The layers whose inputs `analyze_scene` reads from the preset's forward: the layer
    each merge band shows (`maps.merge_bands`), and the last layer (so that the whole aggregator runs, as under
    `--preset`)."""
    from rvggt_jax.diagnostics import maps

    starts = {b[1] for b in maps.merge_bands(comp, geom)} if not comp.is_dense else set()
    return tuple(sorted(starts | {comp.depth - 1}))


def analyze_scene(params, config, images: np.ndarray, names: list[str], comp, out: Path, m: int = 256,
                  seed: int = 0, random_weights: bool = False) -> dict:
    """Every diagnostic of one scene (images [S, 3, H, W]) under preset `comp` (a
    `CompressionConfig`), written to `out` (PNGs and `ANALYSIS_JSON`). Returns the JSON."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from rvggt_jax import diagnostics as D
    from rvggt_jax.compression.partition import Geometry, saliency_protect_count
    from rvggt_jax.diagnostics import maps
    from rvggt_jax.diagnostics.presets_io import preset_dict
    from rvggt_jax.planning.cost import cost_report

    s, _, hh, ww = images.shape
    ps = config.patch_size
    geom = Geometry(s, hh // ps, ww // ps, config.patch_start_idx)
    prof = D.rank_profile(params, images, config, m=m, seed=seed)
    batch = jnp.asarray(images)[None]
    pconf = dataclasses.replace(config, compression=comp)
    bands = maps.merge_bands(comp, geom) if not comp.is_dense else []
    # the preset's own forward: the inputs of the layers that compute a match, and Psi
    kept = preset_forward_layers(comp, geom)
    x, psi, _ = D.layer_inputs(params, batch, pconf, kept, with_output=True)
    slot = {layer: j for j, layer in enumerate(kept)}
    psi_maps = np.asarray(D.saliency_maps(psi, geom.h, geom.w))[0]
    protected = np.asarray(jax.jit(D.protected_patches, static_argnums=(0, 2))(comp, psi, geom))[0]
    files = []
    title = f"attention rank per layer ({s} frames, m = {prof['m']}); bands of preset {comp.name!r}"
    if random_weights:
        title += "\nRANDOM WEIGHTS: meaningless numbers"
    files.append(maps.save_profile_png(out / "rank_profile.png", prof["profile"], comp, title,
                                       per_head=prof["normalised"]).name)
    files.append(maps.save_saliency_png(out / "saliency.png", images, psi_maps, protected).name)
    kv = []
    non_anchor = range(1, s) if comp.anchor else range(s)
    for tile, layers in maps.kv_tiles(comp).items():
        keep = maps.kv_keep_maps(comp, tile, geom)
        union, cov = maps.union_coverage(geom, tile, comp.phase_shift, non_anchor)
        name = f"kv_t{tile[0]}k{tile[1]}.png"
        files.append(maps.save_kv_png(out / name, keep, union, tile, cov, layers).name)
        kv.append(dict(tile=list(tile), layers=layers, kept_fraction_per_frame=_floats(keep.mean(axis=(1, 2))),
                       union_coverage=cov, union_frames=list(non_anchor), image=name))
    groups = []
    group_fn = jax.jit(D.merged_groups, static_argnames=("comp", "layer", "geom", "config"))
    for band, layer, used in bands:
        p_block = params["aggregator"]["global_blocks"][str(layer)]
        g, size = (np.asarray(a)[0] for a in group_fn(p_block, x[slot[layer]], psi, comp=comp, layer=layer,
                                                       geom=geom, config=pconf))
        name = f"groups_{band}.png"
        files.append(maps.save_groups_png(out / name, images, g, size, used, band, layer).name)
        groups.append(dict(band=band, layer=layer, layers=used,
                           in_groups_fraction_per_frame=_floats((size > 1).mean(axis=(1, 2))),
                           groups_of_two_or_more=int(len(np.unique(g[size > 1]))), image=name))
    cost = cost_report(pconf, s, hh, ww)
    doc = dict(
        note=RANDOM_NOTE if random_weights else "measured on the given weights",
        images=names, frames=s, image_hw=[hh, ww], grid=[geom.h, geom.w], tokens=prof["tokens"],
        model=dict(depth=config.depth, num_heads=config.num_heads, embed_dim=config.embed_dim,
                   config=json.loads(json.dumps(config.to_dict(), default=str))),
        rank=dict(m=prof["m"], seed=seed, energy=prof["energy"],
                  query_positions=_floats(D.sample_queries(prof["tokens"], m, seed)),
                  r95=_floats(prof["r95"]), normalised=_floats(prof["normalised"]),
                  profile=_floats(prof["profile"]), spectra=_floats(prof["spectra"])),
        preset=preset_dict(comp),
        saliency=dict(psi=_floats(psi_maps.reshape(s, -1)),
                      protected_per_frame=saliency_protect_count(geom, comp.alpha) if comp.protect == "saliency" else 0,
                      protected=[np.flatnonzero(protected[f].ravel()).tolist() for f in range(s)]),
        kv=kv, merge_bands=groups,
        cost=dict(predicted_speedup=cost["predicted_speedup"],
                  global_attention_ratio=cost["global_attention_ratio"]),
        files=files)
    (out / ANALYSIS_JSON).write_text(json.dumps(doc) + "\n")
    return doc


def run_analyze_command(args) -> int:
    from rvggt_jax.app.model_runner import enable_compilation_cache
    from rvggt_jax.app.outdir import Manifest

    _check_common(args)
    src, out = Path(args.images_dir), Path(args.out)
    if not src.is_dir():
        raise CLIError(f"image folder not found: {src}")
    if args.weights is not None:
        from rvggt_jax.app.commands import _check_weights

        _check_weights(args.weights)
    from rvggt_jax.diagnostics import PresetError, is_preset_path, load_preset

    if is_preset_path(args.preset):  # a bad file fails now, before the model loads
        try:
            load_preset(args.preset)
        except PresetError as e:
            raise CLIError(str(e)) from None
    params, config = _model(args.weights, args.quiet)
    comp = _preset(args.preset, config.depth)
    images, names = _load_scene(src, args)
    _prepare(out, args)
    manifest = Manifest(out)
    enable_compilation_cache()
    random = _is_random(config, args.weights)
    if random:
        warn(RANDOM_NOTE)
    try:
        doc = analyze_scene(params, config, images, names, comp, out, args.m, args.seed, random)
    finally:
        manifest.write()
    prof = doc["rank"]["profile"]
    say(args.quiet, f"analyzed {doc['frames']} frames ({doc['tokens']} tokens, m = {doc['rank']['m']}): r95/m from "
                    f"{min(prof):.3f} to {max(prof):.3f} (peak at L{int(np.argmax(prof)) + 1}); wrote "
                    f"{len(doc['files'])} images and {ANALYSIS_JSON} to {out}")
    return 0


# ---------------------------------------------------------------------------------------
# calibrate
# ---------------------------------------------------------------------------------------


def _read_analysis(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise CLIError(f"cannot read {path}: {one_line(e)}") from None
    except json.JSONDecodeError as e:
        raise CLIError(f"{path} is not valid JSON: {e.msg} at line {e.lineno}") from None
    try:
        prof = doc["rank"]["profile"]
        depth = doc["model"]["depth"]
        if len(prof) != depth or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in prof):
            raise ValueError
    except (KeyError, TypeError, ValueError):
        raise CLIError(f"{path} is not a diagnostics.json written by `rvggt analyze` (no rank profile of one "
                       f"finite value per layer)") from None
    return doc


def run_calibrate_command(args) -> int:
    from rvggt_jax import diagnostics as D
    from rvggt_jax.app.model_runner import enable_compilation_cache
    from rvggt_jax.app.outdir import Manifest
    from rvggt_jax.config import VGGTConfig
    from rvggt_jax.diagnostics.maps import save_profile_png

    _check_common(args)
    if args.name == "dense":
        raise CLIError("--name dense is reserved (it means no compression); choose another name")
    inputs = [Path(i) for i in args.inputs]
    for i in inputs:
        if not i.exists():
            raise CLIError(f"input not found: {i} (a folder of images or a diagnostics.json)")
        if i.is_file() and i.suffix != ".json":
            raise CLIError(f"{i} is neither a folder of images nor a diagnostics.json")
    folders = [i for i in inputs if i.is_dir()]
    params = config = None
    if folders:
        params, config = _model(args.weights, args.quiet)
    out = Path(args.out)
    _prepare(out, args)
    manifest = Manifest(out)
    enable_compilation_cache()
    scenes = []
    try:
        for i in inputs:
            if i.is_dir():
                images, names = _load_scene(i, args)
                say(args.quiet, f"measuring {i} ({images.shape[0]} frames) ...")
                prof = D.rank_profile(params, images, config, m=args.m, seed=args.seed)
                scenes.append(dict(source=str(i), profile=[float(v) for v in prof["profile"]],
                                   frames=int(images.shape[0]), image_hw=list(images.shape[-2:]),
                                   depth=config.depth, random=_is_random(config, args.weights)))
            else:
                doc = _read_analysis(i)
                scenes.append(dict(source=str(i), profile=doc["rank"]["profile"], frames=doc["frames"],
                                   image_hw=doc["image_hw"], depth=doc["model"]["depth"],
                                   random="random" in doc.get("note", ""), model=doc["model"].get("config")))
        depths = {sc["depth"] for sc in scenes}
        if len(depths) != 1:
            raise CLIError(f"the scenes come from models of different depths {sorted(depths)}: calibrate one model")
        if config is None:
            try:
                config = VGGTConfig.from_dict(scenes[0]["model"])
            except Exception as e:
                raise CLIError(f"{scenes[0]['source']}: its model configuration cannot be read ({one_line(e)})") \
                    from None
        mean = D.average_profiles([sc["profile"] for sc in scenes])
        comp, info = D.propose(mean, name=args.name)
        random = any(sc["random"] for sc in scenes)
        if random:
            warn(RANDOM_NOTE)
        ref = scenes[0]
        speed = D.predicted_speedups(config, comp, ref["frames"], *ref["image_hw"])
        # (and at a VGGT-1B workload, when the bands index its 24 layers)
        speed_1b = D.predicted_speedups(VGGTConfig(), comp, 100, 392, 518) if config.depth == 24 else None
        note = (f"rvggt calibrate from {len(scenes)} scene(s); rule in docs/diagnostics.md"
                + (f"; {RANDOM_NOTE}" if random else ""))
        D.save_preset(comp, out / PRESET_JSON, note=note)
        title = f"mean rank profile of {len(scenes)} scene(s); proposed bands of {comp.name!r}"
        if random:
            title += "\nRANDOM WEIGHTS: meaningless numbers"
        save_profile_png(out / "rank_profile.png", mean, comp, title,
                         per_head=np.asarray([sc["profile"] for sc in scenes]).T)
        (out / CALIBRATION_JSON).write_text(json.dumps(dict(
            note=note, scenes=[{k: v for k, v in sc.items() if k != "model"} for sc in scenes],
            mean_profile=[float(v) for v in mean], proposal=info, preset_file=PRESET_JSON,
            predicted_speedup=speed, predicted_speedup_vggt1b_100x392x518=speed_1b), indent=1) + "\n")
    finally:
        manifest.write()
    from rvggt_jax.diagnostics.maps import _ranges

    bands = " / ".join(f"{n} {_ranges(range(a, b)) or '(empty)'}" for n, (a, b) in info["bands"].items())
    say(args.quiet, f"proposed {comp.name!r}: {bands}, merge ratios {list(comp.merge_ratio)}, K/V tiles "
                    f"{[list(t) for t in comp.kv_sigma]}")
    say(args.quiet, f"predicted aggregator speedup over dense at {speed['frames']} frames of "
                    f"{speed['height']}x{speed['width']}: {speed['speedup']:.2f}x (regime {speed['regime_speedup']:.2f}x,"
                    f" ratio {speed['ratio']:.3f})")
    say(args.quiet, f"wrote {out / PRESET_JSON} (use: --preset {out / PRESET_JSON}) and {CALIBRATION_JSON}")
    return 0
