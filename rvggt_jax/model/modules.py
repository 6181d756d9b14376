"""Flax (linen) modules over the pure forward: `VGGT`, `Aggregator` and the heads.

    model = rvggt_jax.model.modules.VGGT(config)
    params = model.init(jax.random.key(0), images)["params"]       # upstream's random init
    out = model.apply({"params": params}, images)                  # == rvggt_forward(params, images, config)

    params, config = rvggt_jax.load_pretrained("facebook/VGGT-1B")  # converted weights: the same tree
    out = rvggt_jax.model.modules.VGGT(config).apply({"params": params}, images, query_points)

One implementation of the math: every module registers its parameters with `self.param`
(one call per leaf, the initialisers of `rvggt_jax.model.initializers`) and then calls the pure
functions `rvggt_forward` is made of (`rvggt_jax.model.forward`, `.aggregator`, `.heads`). Their
parameter trees are the converter's, path for path, so converted weights load as they
are, and `VGGT(config).apply` returns what `rvggt_forward` returns, bit for bit.

A backbone in your own model:

    class MyModel(nn.Module):
        config: VGGTConfig
        @nn.compact
        def __call__(self, images):                       # [B, S, 3, H, W] in [0, 1]
            tokens = Aggregator(self.config, name="backbone")(images)[self.config.depth - 1]
            return nn.Dense(1)(tokens[:, :, 0])           # e.g. from the camera token [B, S, 2C]

    params = MyModel(config).init(key, images)["params"]
    pretrained, _ = rvggt_jax.load_pretrained("facebook/VGGT-1B", skip_track=True)
    params = {**params, "backbone": pretrained["aggregator"]}   # converted weights into the backbone

Names of the modules inside `VGGT` are the converter's top-level keys: "aggregator",
"camera_head", "depth_head", "point_head", "track_head".
"""

from __future__ import annotations

import functools
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.initializers import InitSpec, param_specs

Entries = tuple[tuple[tuple[str, ...], tuple[int, ...], InitSpec], ...]


@functools.lru_cache(maxsize=32)
def _entries(config: VGGTConfig, top: str) -> Entries:
    """The leaves under `top` (a top-level key of the converted tree), paths relative to
    it. Cached: the 1B layout has ~1800 leaves and every trace re-registers them."""
    specs = param_specs(config, skip_track=not config.enable_track)
    return tuple((path[1:], shape, spec) for path, (shape, spec) in specs.items() if path[0] == top)


def _register(module: nn.Module, entries: Entries) -> dict:
    """`module.param` for the depth-1 entries, a `_Leaves` child per first path component
    for the others; returns the nested dict of values (the converter's layout)."""
    out: dict[str, Any] = {}
    groups: dict[str, list] = {}
    for path, shape, spec in entries:
        if len(path) == 1:
            out[path[0]] = module.param(path[0], spec.initializer(), shape, jnp.float32)
        else:
            groups.setdefault(path[0], []).append((path[1:], shape, spec))
    for name, sub in groups.items():
        out[name] = _Leaves(tuple(sub), name=name)()
    return out


class _Leaves(nn.Module):
    """A node of the parameter tree: registers its leaves, recursing into children."""

    entries: Entries

    @nn.compact
    def __call__(self) -> dict:
        return _register(self, self.entries)


class _Part(nn.Module):
    """A module owning the subtree `TOP` of the converted parameter tree."""

    config: VGGTConfig
    TOP = ""

    @nn.compact
    def tree(self) -> dict:
        """This module's parameters as the converter's nested dict (registered on init)."""
        entries = _entries(self.config, self.TOP)
        if not entries:
            raise ValueError(f"{type(self).__name__}: this config has no {self.TOP!r} (is the head enabled?)")
        return _register(self, entries)


def _as_layers(aggregated: Any) -> dict[int, jax.Array]:
    """Aggregator outputs as a dict {layer: [B, S, P, 2C]} (a list of every layer also)."""
    if isinstance(aggregated, dict):
        return aggregated
    if isinstance(aggregated, Sequence):
        return dict(enumerate(aggregated))
    raise TypeError(f"aggregated must be a dict {{layer: [B, S, P, 2C]}} or a list of layers; "
                    f"got {type(aggregated).__name__}")


class Aggregator(_Part):
    """The alternating-attention aggregator (DINOv2 patch embed, `depth` frame and global
    blocks, RegimeVGGT compression per `config.compression`); parameters: the converter's
    `aggregator` subtree, so `params["aggregator"]` of a converted checkpoint loads here.

    `__call__(images, layers=None)`: images [B, S, 3, H, W] or [S, 3, H, W] in [0, 1]
    (H, W multiples of the patch size) -> {layer index: tokens [B, S, P, 2C] float32},
    P = 1 + registers + h*w (the camera token is index 0, patches start at
    `config.patch_start_idx`), for `layers` (default: the layers VGGT's camera and dense
    heads read, e.g. 4, 11, 17, 23 for VGGT-1B)."""

    TOP = "aggregator"

    def __call__(self, images: jax.Array, layers: Sequence[int] | None = None) -> dict[int, jax.Array]:
        from rvggt_jax.model.aggregator import aggregator_forward
        from rvggt_jax.errors import InputError
        from rvggt_jax.model.forward import config_scope
        from rvggt_jax.model.inputs import check_images

        config = self.config.validate()
        p = self.tree()
        images = check_images(images, config)
        keep = tuple(config.needed_layers(False) if layers is None else layers)
        bad = [i for i in keep if not (isinstance(i, int) and 0 <= i < config.depth)]
        if bad or not keep:
            raise InputError(f"layers must be aggregator layer indices in [0, {config.depth}); got {list(keep)}")
        with config_scope(config):
            kept, _, _ = aggregator_forward(p, images, config, set(keep))
            return {i: kept[i].array() for i in sorted(set(keep))}


class CameraHead(_Part):
    """VGGT's camera head (parameters: `camera_head`). `__call__(last_layer)`: the last
    aggregator layer [B, S, P, 2C] -> list of `camera_head.iters` pose encodings
    [B, S, 9] (absT_quaR_FoV), the last one the prediction."""

    TOP = "camera_head"

    def __call__(self, last_layer: jax.Array) -> list[jax.Array]:
        from rvggt_jax.model.forward import config_scope
        from rvggt_jax.model.heads.camera import camera_head

        with config_scope(self.config):
            return camera_head(self.tree(), last_layer[:, :, :1].astype(jnp.float32), self.config.camera_head)


class DPTHead(_Part):
    """VGGT's depth or point head (`output="depth"`: parameters `depth_head`, outputs
    (depth [B, S, H, W, 1], conf [B, S, H, W]); `"point"`: `point_head`, (world points
    [B, S, H, W, 3], conf)). `__call__(aggregated, image_hw)`: aggregator outputs
    {layer: [B, S, P, 2C]} holding `config.dpt_head.intermediate_layer_idx`, image (H, W)."""

    output: str = "depth"

    @property
    def TOP(self) -> str:  # noqa: N802 - the class constant of the other parts
        if self.output not in ("depth", "point"):
            raise ValueError(f"DPTHead output must be 'depth' or 'point'; got {self.output!r}")
        return f"{self.output}_head"

    def __call__(self, aggregated: Any, image_hw: tuple[int, int]) -> tuple[jax.Array, jax.Array]:
        from rvggt_jax.model.forward import config_scope
        from rvggt_jax.model.heads.dpt import depth_head, point_head

        fn = depth_head if self.output == "depth" else point_head
        with config_scope(self.config):
            return fn(self.tree(), _as_layers(aggregated), self.config.dpt_head, self.config.token_grid(image_hw))


class TrackHead(_Part):
    """VGGT's track head (parameters: `track_head`). `__call__(aggregated, images,
    query_points)`: aggregator outputs {layer: [B, S, P, 2C]} holding the track layers,
    images [B, S, 3, H, W] (only the shape is read), query points [B, N, 2] pixel (x, y)
    in frame 0 -> (tracks per iteration [iters, B, S, N, 2], vis [B, S, N], conf [B, S, N])."""

    TOP = "track_head"

    def __call__(self, aggregated: Any, images: jax.Array, query_points: jax.Array):
        from rvggt_jax.model.forward import config_scope
        from rvggt_jax.model.heads.track import track_head

        with config_scope(self.config):
            return track_head(self.tree(), _as_layers(aggregated), self.config.track_head_config,
                              self.config.token_grid(images.shape[-2:]), query_points)


class VGGT(nn.Module):
    """The whole model. `__call__(images, query_points=None)` returns exactly
    `rvggt_forward(params, images, config, query_points)` (see there for every output and
    shape: pose_enc [B, S, 9], depth [B, S, H, W, 1], world_points [B, S, H, W, 3], ...);
    its parameters are the converter's tree (the track head when `config.enable_track`).

    Submodules (names = top-level keys): "aggregator" (`Aggregator`), "camera_head",
    "depth_head", "point_head", "track_head", each as enabled by `config`."""

    config: VGGTConfig

    @nn.compact
    def tree(self) -> dict:
        """Every parameter as the converter's nested dict (registered on init)."""
        c = self.config
        out = {"aggregator": Aggregator(c, name="aggregator").tree()}
        if c.enable_camera:
            out["camera_head"] = CameraHead(c, name="camera_head").tree()
        if c.enable_depth:
            out["depth_head"] = DPTHead(c, "depth", name="depth_head").tree()
        if c.enable_point:
            out["point_head"] = DPTHead(c, "point", name="point_head").tree()
        if c.enable_track:
            out["track_head"] = TrackHead(c, name="track_head").tree()
        return out

    def __call__(self, images: jax.Array, query_points: Any = None) -> dict[str, Any]:
        from rvggt_jax.model.forward import rvggt_forward

        return rvggt_forward(self.tree(), images, self.config, query_points)


def init_params(config: VGGTConfig, key: jax.Array | int = 0) -> dict:
    """A random parameter tree for `config` with upstream's initialisation
    (`rvggt_jax.model.initializers`): `VGGT(config).init(key, images)["params"]` without running the
    forward. Same paths, shapes and dtype (float32) as the converter's tree; `key` is a
    PRNG key or an int seed. For no allocation at all (e.g. the 1B layout's shapes):
    `jax.eval_shape(init_params, config, jax.random.PRNGKey(0))`."""
    if not isinstance(config, VGGTConfig):
        raise TypeError(f"config must be a VGGTConfig; got {type(config).__name__}")
    config.validate()
    if isinstance(key, int):
        key = jax.random.PRNGKey(key)
    return VGGT(config).init(key, method=VGGT.tree)["params"]
