"""VGGT track head: a feature-only DPT (down ratio 2, no positional embedding) followed by
the iterative point tracker of `rvggt_jax.model.heads.tracker`.

Parameters are the `track_head` subtree of the converted state dict: `feature_extractor`
(DPT layout, see `rvggt_jax.model.heads.dpt`) and `tracker` (see `rvggt_jax.model.heads.tracker`).
"""

from __future__ import annotations

from typing import Callable

import jax

from rvggt_jax.config import TokenGrid, TrackHeadConfig
from rvggt_jax.model.heads.dpt import Aggregated, dpt_features
from rvggt_jax.model.heads.tracker import track_predictor
from rvggt_jax.model.params import Params


# Upstream TrackHead builds its DPT extractor with these fixed settings.
FEATURE_DOWN_RATIO = 2


def track_features(params: Params, aggregated: Aggregated, config: TrackHeadConfig, grid: TokenGrid,
                   remat: Callable | None = None) -> jax.Array:
    """The track head's DPT feature maps: [B, S, H/2, W/2, features] (NHWC), with H, W the
    image size rounded down to multiples of the patch size. `remat`: see
    `dpt.map_frame_groups`."""
    if config.intermediate_layer_idx is None:
        raise ValueError("the track head's intermediate_layer_idx is unset: pass VGGTConfig.track_head_config")
    return dpt_features(params["feature_extractor"], aggregated, grid, layer_idx=config.intermediate_layer_idx,
                        down_ratio=FEATURE_DOWN_RATIO, pos_embed=False, remat=remat, reader="track_head")


def track_head(params: Params, aggregated: Aggregated, config: TrackHeadConfig, grid: TokenGrid,
               query_points: jax.Array, *, iters: int | None = None,
               remat: Callable | None = None) -> tuple[jax.Array, jax.Array, jax.Array | None]:
    """Upstream `TrackHead.forward`.

    params: the `track_head` subtree. aggregated: aggregator outputs, each [B, S, P, 2E]
    (a list of every layer, or a dict {layer index: tokens} holding at least
    `config.intermediate_layer_idx`). config: the track head's sub-config with its
    extractor's layers filled in (`VGGTConfig.track_head_config`). grid: the images'
    `TokenGrid`. query_points [B, N, 2]: pixel (x, y) in frame 0; an unbatched [N, 2]
    array is rejected, as by upstream's head (the full model adds the batch axis before
    calling it). iters: refinement iterations, default `config.iters`.

    Returns (track_list [iters, B, S, N, 2] pixel (x, y), one entry per iteration, the last
    being the prediction; vis [B, S, N] and conf [B, S, N] in (0, 1), conf None when
    `config.predict_conf` is off); with the frames split over devices, those of this
    device (see `track_predictor`). `remat`: how the feature extractor's frame groups run in a
    training step (`dpt.map_frame_groups`).
    """
    if query_points.ndim != 3 or query_points.shape[-1] != 2:
        raise ValueError(f"query_points must be [B, N, 2] (add the batch axis to [N, 2]), "
                         f"got shape {query_points.shape}")
    fmaps = track_features(params, aggregated, config, grid, remat)
    return track_predictor(params["tracker"], query_points, fmaps, config, iters=iters)
