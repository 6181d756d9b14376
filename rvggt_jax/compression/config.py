"""Compression configuration of the global blocks (RegimeVGGT and the presets it subsumes).

`CompressionConfig` is a frozen, hashable dataclass (tuples only) that lives inside
`VGGTConfig`, so it is part of the jitted function's static identity: every array shape
of the compressed forward pass is a function of the input shape and this configuration.

Per-band fields hold three values (shallow, middle, deep); the band boundaries are
configuration too (`merge_bands`, `kv_bands`). A per-band field may also hold one value
per global layer (a tuple of length `depth`), or a single number for every layer.

K/V rates: `kv_sigma` entries are a sigma (1.0 = no K/V downsampling; 1.3, 1.5, 1.7 and
integers map to tiles as the authors do, see `sigma_to_tile`) or an explicit
`(tile, kept)` pair: patch (i, j) of frame f is kept when ((i - r_f) mod t) < k and
((j - c_f) mod t) < k inside the truncated grid, i.e. a kept fraction (k/t)^2.

See docs/method.md for every choice and the deviations from the authors' code.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import Any, Mapping

from rvggt_jax.compression.presets import PRESET_OVERRIDES
from rvggt_jax.errors import InputError  # a ValueError: `except ValueError` still catches it


class LayerKind(enum.StrEnum):
    """What a global layer does, the one vocabulary of the configuration and the plans.

    The configuration says DENSE, FRAME or COMPRESSED (`CompressionConfig.layer_kind`);
    the static plan of a COMPRESSED layer (`plan.layer_plan`) decides between MERGE
    (r > 0 tokens merged, K/V possibly subsampled), KV (no merging, K/V subsampled) and
    DENSE (nothing to compress)."""

    DENSE = "dense"
    FRAME = "frame"  # attention within each frame
    COMPRESSED = "compressed"
    MERGE = "merge"
    KV = "kv"

PROTECT_MODES = ("saliency", "stride", "none")
MATCH_SCOPES = ("sequence", "frame")
MATCH_METRICS = ("auto", "input", "norm1")


def sigma_to_tile(sigma: Any) -> tuple[int, int]:
    """K/V rate -> (tile t, kept k) with kept fraction (k/t)^2 ~ 1/sigma^2, as the authors
    map it: 1 -> (1, 1) (no downsampling), 1.3 -> (4, 3), 1.5 -> (3, 2), 1.7 -> (5, 3),
    an integer n >= 2 -> (n, 1). An explicit (t, k) pair with 1 <= k <= t passes through."""
    if isinstance(sigma, (tuple, list)):
        if len(sigma) != 2:
            raise ValueError(f"a K/V tile is a (tile, kept) pair; got {sigma!r}")
        t, k = int(sigma[0]), int(sigma[1])
        if t < 1 or not 1 <= k <= t or (t, k) != tuple(sigma):
            raise ValueError(f"K/V tile needs integers 1 <= kept <= tile; got {sigma!r}")
        return (1, 1) if k == t else (t, k)
    s = float(sigma)
    for value, tile in ((1.3, (4, 3)), (1.5, (3, 2)), (1.7, (5, 3))):
        if abs(s - value) < 1e-6:
            return tile
    n = int(round(s))
    if n < 1 or abs(s - n) > 1e-6:
        raise ValueError(f"K/V sigma must be 1, 1.3, 1.5, 1.7, an integer >= 2 or a (tile, kept) pair; got {sigma!r}")
    return (1, 1) if n == 1 else (n, 1)


def _freeze(value: Any) -> Any:
    """Lists (from JSON) -> tuples, recursively, so the config stays hashable."""
    if isinstance(value, (list, tuple)):
        return tuple(_freeze(v) for v in value)
    return value


def _band_index(layer: int, bands: tuple[int, int]) -> int:
    return 0 if layer < bands[0] else (1 if layer < bands[1] else 2)


def _per_layer(value: Any, layer: int, depth: int, bands: tuple[int, int], field: str) -> Any:
    """Resolve a per-band / per-layer / scalar field at one layer."""
    if not isinstance(value, tuple) or (field == "kv_sigma" and _is_tile(value)):
        return value
    if len(value) == 3 and depth != 3:
        return value[_band_index(layer, bands)]
    if len(value) == depth:
        return value[layer]
    raise ValueError(f"{field} needs 3 per-band values or {depth} per-layer values; got {len(value)}")


def _is_tile(value: Any) -> bool:
    return isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value)


@dataclass(frozen=True)
class CompressionConfig:
    """How every global block is compressed. `name == "dense"`: the upstream block.

    Token merging (axis 1)
      merge_ratio        rho per band (shallow, middle, deep) or per layer; 0 = no merging.
      merge_bands        first layer of the middle and deep merge bands.
      match_scope        "sequence" (the authors: each src may match any dst of the
                         sequence) or "frame" (src only match dst of their own frame).
      match_metric       cosine-similarity features: "input" (block input), "norm1" (its
                         norm1 output) or "auto" (input where K/V is downsampled, norm1 in
                         merge-only layers, as the authors' code).
      cache_band_starts  layers where a match cache band starts; the match computed at
                         the first layer of a band is reused by the later layers of that
                         band with the same merge ratio. () = no cache.
      no_cache_layers    layers that always recompute their match (and do not store it).
      protect            "saliency": top max(1, floor(alpha*T)) patches under Psi of every
                         frame >= 1 are never merged; "stride": every
                         (N // floor(alpha*N))-th token of the sequence (FastVGGT);
                         "none".
      alpha              protected fraction.
      size_bias          log(group size) added to the attention logits (proportional
                         attention), folded into an extra Q/K column.
      duplicate_protected  reproduce the authors' artefact of the protected dst tokens
                         appearing twice among the keys/values (protected src appear
                         once, as the authors'; off: no duplicate), each protected
                         token's own query attending too, a protected dst taking its
                         output (the authors' unmerge writes those rows last).
      duplicate_capacity the rows (queries and K/V slots) a layer gives the protected dst's
                         own copies under saliency protection, as a multiple of their
                         expected count (at most every protected token): which protected
                         tokens are dst depends on the data, so a sequence with more
                         protected dst than that runs the layer's attention with every
                         protected token's row (a second branch of the layer, same
                         values). Stride protection counts them exactly.
      dst_seed           seed of the fixed per-cell dst choice; -1 = top-left of every cell.

    K/V downsampling (axis 2)
      kv_sigma           K/V rate per band or per layer: sigma or (tile, kept).
      kv_bands           first layer of the middle and deep K/V bands.
      merge_only_layers  layers without K/V downsampling whatever kv_sigma says.
      anchor             frame 0 keeps all its K/V.
      phase_shift        per-frame offsets r_f = (f div t) mod t, c_f = f mod t.
      kv_protect_saliency  Psi-protected patches are always kept in K/V (paper text).
      kv_capacity        the data-dependent K/V slots (unmerged src on the sub-grid) a
                         merging layer attends with, as a multiple of their expected
                         count (at most the bound, every unmerged src that can be on the
                         sub-grid): a sequence with more filled runs the layer's attention
                         with every slot (a second branch, same values). On one device;
                         frame-sharded runs attend with every slot.

    Layer kinds
      frame_layers       global attention restricted to each frame (AVGGT's G2F).
      dense_layers       the upstream block, untouched.

    Attention
      head_pad_multiple  for the cost model: the folded head dimension d+1 that a flash
                         kernel sees, rounded up to a multiple of this (8 for cuDNN;
                         1: unpadded). The attention op (`rvggt_jax.ops.attention`) pads as
                         its kernel needs; on CPU the bias is added to the logits.
      match_chunk        src tokens per similarity chunk; 0 = one chunk.
      merge_head_groups  a merging layer runs its means, keys and attention for this many
                         groups of heads, one group after another (at most one per head):
                         the float32 group sums and the merged q, k, v of one group exist
                         at a time, a fraction of one layer's K/V (exact: heads attend
                         independently). The price: norm1 of the tokens recomputed per group.
    """

    name: str = "dense"
    depth: int = 24
    merge_ratio: Any = (0.0, 0.0, 0.0)
    merge_bands: tuple[int, int] = (10, 18)
    match_scope: str = "sequence"
    match_metric: str = "auto"
    cache_band_starts: tuple[int, ...] = ()
    no_cache_layers: tuple[int, ...] = ()
    protect: str = "saliency"
    alpha: float = 0.1
    size_bias: bool = True
    duplicate_protected: bool = False
    duplicate_capacity: float = 1.5
    dst_seed: int = 33
    kv_sigma: Any = (1.0, 1.0, 1.0)
    kv_bands: tuple[int, int] = (10, 14)
    merge_only_layers: tuple[int, ...] = ()
    anchor: bool = True
    phase_shift: bool = True
    kv_protect_saliency: bool = False
    kv_capacity: float = 1.5
    frame_layers: tuple[int, ...] = ()
    dense_layers: tuple[int, ...] = ()
    head_pad_multiple: int = 1
    match_chunk: int = 1024
    merge_head_groups: int = 4

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, _freeze(getattr(self, f.name)))
        if self.protect not in PROTECT_MODES:
            raise ValueError(f"protect must be one of {PROTECT_MODES}; got {self.protect!r}")
        if self.match_scope not in MATCH_SCOPES:
            raise ValueError(f"match_scope must be one of {MATCH_SCOPES}; got {self.match_scope!r}")
        if self.match_metric not in MATCH_METRICS:
            raise ValueError(f"match_metric must be one of {MATCH_METRICS}; got {self.match_metric!r}")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1]; got {self.alpha}")
        if not self.duplicate_capacity >= 0.0:
            raise ValueError(f"duplicate_capacity must be >= 0; got {self.duplicate_capacity}")
        if not self.kv_capacity >= 0.0:
            raise ValueError(f"kv_capacity must be >= 0; got {self.kv_capacity}")
        if self.head_pad_multiple < 1:
            raise ValueError("head_pad_multiple must be >= 1")
        if not isinstance(self.merge_head_groups, int) or self.merge_head_groups < 1:
            raise ValueError(f"merge_head_groups must be an integer >= 1; got {self.merge_head_groups!r}")
        for layer in range(self.depth):
            rho = self.layer_merge_ratio(layer)
            if not 0.0 <= rho < 1.0:
                raise ValueError(f"merge ratio must be in [0, 1); layer {layer} has {rho}")
            self.layer_tile(layer)  # validates the sigma

    # ---- per-layer resolution ----------------------------------------------------------
    @property
    def is_dense(self) -> bool:
        return self.name == "dense"

    def layer_merge_ratio(self, layer: int) -> float:
        return float(_per_layer(self.merge_ratio, layer, self.depth, self.merge_bands, "merge_ratio"))

    def layer_tile(self, layer: int) -> tuple[int, int]:
        if layer in self.merge_only_layers:
            return (1, 1)
        return sigma_to_tile(_per_layer(self.kv_sigma, layer, self.depth, self.kv_bands, "kv_sigma"))

    def layer_kind(self, layer: int) -> LayerKind:
        """DENSE | FRAME | COMPRESSED (the shape plan may still reduce a compressed layer
        with nothing to compress to the dense block)."""
        if self.is_dense or layer in self.dense_layers:
            return LayerKind.DENSE
        if layer in self.frame_layers:
            return LayerKind.FRAME
        return LayerKind.COMPRESSED

    def layer_metric(self, layer: int) -> str:
        if self.match_metric != "auto":
            return self.match_metric
        return "norm1" if self.layer_tile(layer) == (1, 1) else "input"

    def cache_key(self, layer: int) -> str | None:
        """Match-cache key of a layer (None: computed fresh, not stored): the cache band
        and the merge ratio, as the authors key their cache."""
        if not self.cache_band_starts or layer in self.no_cache_layers:
            return None
        starts = sorted(set(self.cache_band_starts))
        band = sum(1 for s in starts if s <= layer) - 1
        if band < 0:
            return None
        return f"band{band}_rho{self.layer_merge_ratio(layer):.4f}"

    # ---- JSON ----------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CompressionConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"CompressionConfig: unknown keys {unknown}")
        return cls(**{k: _freeze(v) for k, v in d.items()})


PRESETS = tuple(PRESET_OVERRIDES)


def make_compression(name: str, depth: int = 24, **overrides: Any) -> CompressionConfig:
    """The named preset for `depth` global layers, fields overridden by name, e.g.
    `make_compression("regime", 24, merge_ratio=(0, 0, 0), kv_sigma=(1, 1, 1))`.

    Layer lists of the presets are written for 24 layers; for another depth they are
    rescaled proportionally (band starts and layer sets). An unknown preset or field is an
    `rvggt_jax.InputError` naming the known ones."""
    if name not in PRESET_OVERRIDES:
        raise InputError(f"unknown compression preset {name!r}; known: {', '.join(PRESETS)}")
    fields = dict(PRESET_OVERRIDES[name])
    if depth != 24:
        fields = _rescale(fields, depth)
    fields.update(overrides)
    fields["name"] = name
    fields["depth"] = depth
    known = {f.name for f in dataclasses.fields(CompressionConfig)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise InputError(f"unknown compression fields {unknown}; known: {sorted(known)}")
    return CompressionConfig(**fields)


_LAYER_FIELDS = ("cache_band_starts", "no_cache_layers", "merge_only_layers", "frame_layers", "dense_layers")
_BAND_FIELDS = ("merge_bands", "kv_bands")


def _rescale(fields: dict[str, Any], depth: int) -> dict[str, Any]:
    """Map the 24-layer indices of a preset onto `depth` layers: new layer j stands for
    old layer floor(24 j / depth); a band starting at old layer s starts at the first j
    standing for a layer >= s."""
    def old(j: int) -> int:
        return (j * 24) // depth

    def start(s: int) -> int:
        return next((j for j in range(depth) if old(j) >= s), depth)

    out = dict(fields)
    for k in _BAND_FIELDS:
        if k in out:
            out[k] = tuple(start(i) for i in out[k])
    for k in _LAYER_FIELDS:
        if k in out:
            members = set(out[k])
            if k == "cache_band_starts":
                out[k] = tuple(sorted({start(i) for i in members if start(i) < depth}))
            else:
                out[k] = tuple(j for j in range(depth) if old(j) in members)
    return out
