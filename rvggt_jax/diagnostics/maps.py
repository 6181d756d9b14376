"""The paper's maps of a scene under a compression preset: the DINOv2 [CLS] saliency Psi
of every frame, the Psi-protected patches, the K/V positions each frame keeps (the
phase-shifted sub-grid) with their union over frames, and the merged groups of each
merge band. Array functions first (jit-able where they run on the forward's arrays),
then the PNG writers (matplotlib, headless).

Shapes: S frames of an h x w patch grid; Psi [B, S, h*w] as the forward returns it
(`VGGTConfig.with_outputs(saliency=True)`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.compression.config import CompressionConfig, LayerKind
from rvggt_jax.diagnostics.calibrate import GO
from rvggt_jax.compression.partition import Geometry, grid_keep, kv_static_keep

# ---------------------------------------------------------------------------------------
# arrays
# ---------------------------------------------------------------------------------------


def saliency_maps(saliency: jax.Array, h: int, w: int) -> jax.Array:
    """Psi [B, S, h*w] -> [B, S, h, w] (the same values, on the patch grid; jit-able)."""
    b, s, t = saliency.shape
    if t != h * w:
        raise ValueError(f"saliency has {t} patches per frame but the grid is {h} x {w}")
    return saliency.reshape(b, s, h, w)


def protected_patches(comp: CompressionConfig, saliency: jax.Array, geom: Geometry) -> jax.Array:
    """[B, S, h, w] bool: the patches the preset never merges, as the forward protects them
    (`compression.init_state`: top max(1, floor(alpha*T)) under Psi in frames >= 1, or
    FastVGGT's stride); all False without protection or under the dense preset. Jit-able."""
    from rvggt_jax.compression.state import init_state

    b = saliency.shape[0]
    state = None if comp.is_dense else init_state(comp, saliency, geom)
    if state is None or state.protected is None:  # (dense merges nothing: nothing to protect)
        return jnp.zeros((b, geom.frames, geom.h, geom.w), bool)
    flags = state.protected.reshape(b, geom.frames, geom.per_frame)[:, :, geom.num_special:]
    return flags.reshape(b, geom.frames, geom.h, geom.w)


def kv_tiles(comp: CompressionConfig) -> dict[tuple[int, int], list[int]]:
    """{K/V tile (t, k): the global layers that subsample with it} (compressed layers
    with t > 1; merge-only, dense and frame layers have no sub-grid)."""
    out: dict[tuple[int, int], list[int]] = {}
    for layer in range(comp.depth):
        tile = comp.layer_tile(layer)
        if tile != (1, 1) and comp.layer_kind(layer) == LayerKind.COMPRESSED:
            out.setdefault(tile, []).append(layer)
    return out


def kv_keep_maps(comp: CompressionConfig, tile: tuple[int, int], geom: Geometry) -> np.ndarray:
    """[S, h, w] bool: the patches of each frame kept as K/V for static reasons at a layer
    of K/V tile `tile` (the phase-shifted sub-grid, frame 0 whole when anchored;
    `partition.kv_static_keep`)."""
    keep = kv_static_keep(geom, tuple(tile), comp.phase_shift, comp.anchor)
    return keep.reshape(geom.frames, geom.per_frame)[:, geom.num_special:].reshape(geom.frames, geom.h, geom.w)


def union_coverage(geom: Geometry, tile: tuple[int, int], phase_shift: bool = True,
                   frames: Sequence[int] | None = None) -> tuple[np.ndarray, float]:
    """The phase-shift argument: ([h, w] bool union of the sub-grid positions kept by
    `frames` (default every frame), the fraction of the truncated grid
    (h div t)*t x (w div t)*t it covers). The anchor is left out on purpose: a whole frame
    would make any union full."""
    t = tile[0]
    frames = range(geom.frames) if frames is None else frames
    ii, jj = np.meshgrid(np.arange(geom.h), np.arange(geom.w), indexing="ij")
    union = np.zeros((geom.h, geom.w), bool)
    for f in frames:
        union |= grid_keep(ii, jj, np.full_like(ii, f), geom.h, geom.w, tuple(tile), phase_shift)
    th, tw = (geom.h // t) * t, (geom.w // t) * t
    if th * tw == 0:
        return union, 0.0
    return union, float(union[:th, :tw].mean())


BAND_NAMES = ("shallow", "middle", "deep")


def merge_bands(comp: CompressionConfig, geom: Geometry) -> list[tuple[str, int, list[int]]]:
    """[(band name, the layer whose match the figure shows, the band's merging layers)]
    for the shallow / middle / deep bands of `comp.merge_bands` that merge on this
    sequence. The layer shown is the band's first that computes its match (a band whose
    layers all reuse an earlier band's match shows the layer that computed it)."""
    from rvggt_jax.compression.plan import layer_plan

    lo, hi = comp.merge_bands
    spans = ((0, lo), (lo, hi), (hi, comp.depth))
    plans = {i: layer_plan(comp, i, geom) for i in range(comp.depth) if comp.layer_kind(i) == LayerKind.COMPRESSED}
    merging = [i for i, p in plans.items() if p.kind == LayerKind.MERGE]
    out = []
    for name, (a, b) in zip(BAND_NAMES, spans):
        layers = [i for i in merging if a <= i < min(b, comp.depth)]
        if not layers:
            continue
        shown = next((i for i in layers if plans[i].match == "compute"), None)
        if shown is None:  # every layer of the band reuses a match computed before it
            key = plans[layers[0]].match_key
            shown = next(i for i in merging if plans[i].match == "compute" and plans[i].match_key == key)
        out.append((name, shown, layers))
    return out


def merged_groups(p_block, x: jax.Array, saliency: jax.Array, comp: CompressionConfig, layer: int,
                  geom: Geometry, config) -> tuple[jax.Array, jax.Array]:
    """The match the preset computes at global layer `layer` (`merge_bands`' layer) from
    the block's input x [B, N, C] (N = S * P) and Psi [B, S, h*w]: (group [B, S, h, w]
    int32, every patch's group in the query layout; size [B, S, h, w] float32, the size of
    that group). Patches sharing a group are merged. Jit-able."""
    from rvggt_jax.compression.merged_layer import layer_match
    from rvggt_jax.compression.plan import layer_plan
    from rvggt_jax.compression.state import init_state

    plan = layer_plan(comp, layer, geom)
    if plan.kind != LayerKind.MERGE:
        raise ValueError(f"global layer {layer} does not merge under preset {comp.name!r} ({plan.kind})")
    match, _ = layer_match(p_block, x, plan, config, init_state(comp, saliency, geom))
    b = x.shape[0]
    size = jnp.take_along_axis(match.sizes, match.group, axis=1)  # [B, N]
    patches = lambda a: a.reshape(b, geom.frames, geom.per_frame)[:, :, geom.num_special:].reshape(
        b, geom.frames, geom.h, geom.w)
    return patches(match.group), patches(size)


# ---------------------------------------------------------------------------------------
# PNGs
# ---------------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    return plt


def _frames_figure(n: int, title: str, scale: float = 2.6):
    plt = _plt()
    fig, axes = plt.subplots(1, n, figsize=(scale * n + 0.4, scale * 0.9 + 0.5), squeeze=False)
    fig.suptitle(title, fontsize=9)
    for ax in axes[0]:
        ax.set_axis_off()
    return fig, axes[0]


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80, bbox_inches="tight")
    _plt().close(fig)
    return path


def _image_hwc(image: np.ndarray) -> np.ndarray:
    """[3, H, W] in [0, 1] -> [H, W, 3]."""
    return np.clip(np.transpose(np.asarray(image, np.float32), (1, 2, 0)), 0, 1)


def save_saliency_png(path: Path, images: np.ndarray, psi: np.ndarray, protected: np.ndarray) -> Path:
    """Psi of every frame over its image (images [S, 3, H, W], psi [S, h, w]), the
    protected patches outlined in cyan (protected [S, h, w] bool)."""
    s = psi.shape[0]
    fig, axes = _frames_figure(s, "saliency Psi (DINOv2 [CLS] attention), protected patches in cyan")
    for f, ax in enumerate(axes):
        img = _image_hwc(images[f])
        hh, ww = img.shape[:2]
        ax.imshow(img)
        ax.imshow(psi[f], cmap="inferno", alpha=0.6, extent=(0, ww, hh, 0), interpolation="nearest")
        ph, pw = hh / psi.shape[1], ww / psi.shape[2]
        for i, j in zip(*np.nonzero(protected[f])):
            ax.add_patch(_plt().Rectangle((j * pw, i * ph), pw, ph, fill=False, edgecolor="cyan", linewidth=0.8))
        ax.set_title(f"frame {f}" + (" (reference)" if f == 0 else ""), fontsize=8)
    return _save(fig, path)


def save_kv_png(path: Path, keep: np.ndarray, union: np.ndarray, tile: tuple[int, int], coverage: float,
                layers: Sequence[int]) -> Path:
    """The K/V positions each frame keeps (keep [S, h, w]) and their union over the
    non-anchor frames (union [h, w]) for one K/V tile."""
    s = keep.shape[0]
    t, k = tile
    fig, axes = _frames_figure(s + 1, f"kept K/V patches, tile (t, k) = ({t}, {k}) (kept (k/t)^2 = {(k / t) ** 2:.3f}), "
                                      f"layers {_ranges(layers)}; union over frames covers {coverage:.1%}")
    for f in range(s):
        axes[f].imshow(keep[f], cmap="Greens", vmin=0, vmax=1.3, interpolation="nearest")
        axes[f].set_title(f"frame {f}: {keep[f].mean():.0%}", fontsize=8)
    axes[s].imshow(union, cmap="Blues", vmin=0, vmax=1.3, interpolation="nearest")
    axes[s].set_title(f"union: {coverage:.0%}", fontsize=8)
    return _save(fig, path)


def save_groups_png(path: Path, images: np.ndarray, group: np.ndarray, size: np.ndarray, layers: Sequence[int],
                    band: str = "", shown: int | None = None) -> Path:
    """The merged groups of one merge band (group, size [S, h, w], the match of layer
    `shown`): every patch of a group of two or more in its group's colour, unmerged
    patches grey."""
    s = group.shape[0]
    rng = np.random.default_rng(0)
    palette = rng.uniform(0.15, 1.0, (int(group.max()) + 1, 3))
    which = f"{band} band {_ranges(layers)}" + ("" if shown is None else f", match of L{shown + 1}")
    fig, axes = _frames_figure(s, f"merged groups, {which} (one colour per group; grey: alone)")
    for f, ax in enumerate(axes):
        img = _image_hwc(images[f])
        colours = np.where((size[f] > 1)[..., None], palette[group[f]], 0.5)
        hh, ww = img.shape[:2]
        ax.imshow(img)
        ax.imshow(colours, alpha=0.65, extent=(0, ww, hh, 0), interpolation="nearest")
        ax.set_title(f"frame {f}: {np.mean(size[f] > 1):.0%} in groups", fontsize=8)
    return _save(fig, path)


def save_profile_png(path: Path, profile: np.ndarray, comp: CompressionConfig | None, title: str,
                     per_head: np.ndarray | None = None) -> Path:
    """The rank profile: layer (1-based, the paper's L1..) x r95/m, per-head values as
    dots, the merge bands of `comp` shaded (shallow / middle / deep)."""
    plt = _plt()
    depth = len(profile)
    fig, ax = plt.subplots(figsize=(6.4, 3.2))
    x = np.arange(1, depth + 1)
    if comp is not None and not comp.is_dense:
        lo, hi = comp.merge_bands
        for (a, b), colour, name in (((0, lo), "#9ecae1", "shallow"), ((lo, hi), "#fdae6b", "middle"),
                                     ((hi, depth), "#a1d99b", "deep")):
            if b > a:
                ax.axvspan(a + 0.5, b + 0.5, color=colour, alpha=0.35, lw=0)
                ax.text((a + b) / 2 + 0.5, 1.02, name, ha="center", va="bottom", fontsize=7,
                        transform=ax.get_xaxis_transform())
    if per_head is not None:
        for h in range(per_head.shape[1]):
            ax.plot(x, per_head[:, h], ".", color="grey", ms=3, alpha=0.6)
    ax.plot(x, profile, "o-", color="black", ms=4, lw=1.2, label="mean over heads")
    ax.axhline(GO, color="green", ls=":", lw=1, label=f"{GO} (paper's go-criterion)")
    ax.set_xlabel("global layer")
    ax.set_ylabel("r95 / m")
    ax.set_xlim(0.5, depth + 0.5)
    ax.set_ylim(0, max(0.35, float(np.max(profile)) * 1.15 if len(profile) else 1))
    ax.set_title(title, fontsize=9, pad=14)
    ax.legend(fontsize=7, loc="upper right")
    return _save(fig, path)


def _ranges(layers: Sequence[int]) -> str:
    """0-based layer indices as the paper's 1-based ranges: [0..9, 12] -> 'L1-L10, L13'."""
    out, layers = [], sorted(layers)
    i = 0
    while i < len(layers):
        j = i
        while j + 1 < len(layers) and layers[j + 1] == layers[j] + 1:
            j += 1
        out.append(f"L{layers[i] + 1}" + (f"-L{layers[j] + 1}" if j > i else ""))
        i = j + 1
    return ", ".join(out)
