"""Compression through the whole model on the tiny upstream checkpoint
(tests/data/vggt_tiny): rho = 0 and sigma = 1 equals dense; every preset compiles once
per input shape and returns finite outputs; the long-sequence routes (periodic RoPE
tables, every loop in chunks) equal one chunk."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.helpers import rel_err
from rvggt_jax import rvggt_forward
from rvggt_jax.compression import PRESETS

OUTPUTS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")


@pytest.fixture(scope="module")
def dense_out(tiny, golden):
    params, config = tiny
    return jax.tree.map(np.asarray, jax.jit(rvggt_forward)(params, golden["images"], config))


@pytest.fixture(scope="module")
def preset_forward(tiny, golden):
    """A preset's forward, compiled once for the module: name -> (the jitted forward, its
    traces, its outputs on the fixture's images). The preset test runs it on a second image
    set; the long-sequence test takes its outputs as the reference (the same program)."""
    params, config = tiny
    runs = {}

    def run(name):
        if name not in runs:
            cfg = config.with_compression(name)
            traces = []

            def forward(p, x):
                traces.append(1)
                return rvggt_forward(p, x, cfg)

            fwd = jax.jit(forward)
            runs[name] = fwd, traces, jax.tree.map(np.asarray, fwd(params, golden["images"]))
        return runs[name]

    return run


def test_regime_without_compression_equals_dense(tiny, golden, dense_out):
    params, config = tiny
    cfg = config.with_compression("regime", merge_ratio=(0.0, 0.0, 0.0), kv_sigma=(1.0, 1.0, 1.0))
    out = jax.jit(rvggt_forward)(params, golden["images"], cfg)
    for key in OUTPUTS:
        assert rel_err(out[key], dense_out[key]) <= 1e-5, key
    for a, b in zip(out["pose_enc_list"], dense_out["pose_enc_list"]):
        assert rel_err(a, b) <= 1e-5


@pytest.mark.parametrize("name", [p for p in PRESETS if p != "dense"])
def test_every_preset_compiles_once_and_is_finite(tiny, golden, dense_out, preset_forward, name):
    params, config = tiny
    images = golden["images"]
    other = np.ascontiguousarray(images[..., ::-1, :])  # another image set of the same shape
    fwd, traces, a = preset_forward(name)  # (a = fwd(params, images))
    b = jax.tree.map(np.asarray, fwd(params, other))
    assert fwd._cache_size() == 1 and len(traces) == 1
    for key in OUTPUTS:
        assert a[key].shape == dense_out[key].shape
        assert np.isfinite(a[key]).all() and np.isfinite(b[key]).all(), key
    assert not np.allclose(a["depth"], b["depth"])
    # compression changes the result, but not beyond recognition on this tiny model
    assert not np.array_equal(a["pose_enc"], dense_out["pose_enc"])


def test_scanned_bands_equal_the_layer_by_layer_loop(tiny, golden):
    # The aggregator runs each band as two lax.scans (the layer computing the band's match,
    # then the layers reusing it); the same layers one by one through `global_block`
    # (checked against the float64 reference of the method in tests/compression/test_block.py)
    # must agree.
    from rvggt_jax import compression
    from rvggt_jax.model import layers
    from rvggt_jax.model.aggregator import aggregator_forward, layer_groups, special_tokens
    from rvggt_jax.compression import Geometry
    from rvggt_jax.model.patch_embed import patch_embed

    params, config = tiny
    cfg = config.with_compression("regime")
    images = golden["images"]
    b, s, _, hh, ww = images.shape
    h, w = hh // 14, ww // 14
    assert layer_groups(cfg, Geometry(s, h, w, cfg.patch_start_idx)) == (
        (0,), tuple(range(1, 10)), (10, 11, 12, 13), (14,), (15, 16, 17), (18,), tuple(range(19, 24)))

    def loop(p, images):
        tokens, sal = patch_embed(p["patch_embed"], images, cfg)
        x = jnp.concatenate([special_tokens(p["camera_token"], b, jnp.arange(s)), special_tokens(p["register_token"], b, jnp.arange(s)),
                             tokens], axis=1)
        n, num, c = x.shape
        pos = layers.RopeTables.from_positions(jnp.asarray(layers.patch_positions(h, w, 5))[None], cfg.head_dim,
                                               cfg.rope_freq)
        gpos = jax.tree.map(lambda t: jnp.tile(t, (1, s, 1, 1)), pos)
        state = compression.init_state(cfg.compression, sal, Geometry(s, h, w, cfg.patch_start_idx))
        out = []
        for i in range(cfg.depth):
            x = layers.sequence_block(p["frame_blocks"][str(i)], x.reshape(b * s, num, c), pos,
                                      layers.BlockConfig(cfg.num_heads, rope_freq=cfg.rope_freq))
            f = x.reshape(b, s, num, c)
            x, state = compression.global_block(p["global_blocks"][str(i)], x.reshape(b, s * num, c), gpos, i, cfg,
                                                state)
            out.append(jnp.concatenate([f, x.reshape(b, s, num, c)], axis=-1))
        return out

    ref = jax.jit(loop)(params["aggregator"], images)
    scanned, _, _ = jax.jit(lambda p, x: aggregator_forward(p, x, cfg, range(24)))(params["aggregator"], images)
    for i in range(cfg.depth):
        assert rel_err(scanned[i].array(), ref[i]) <= 1e-5, i


@pytest.mark.parametrize("name", ["regime", "avggt"])  # merged layers; frame and K/V-only layers
def test_long_sequence_routes_equal_one_chunk(tiny, golden, monkeypatch, preset_forward, name):
    # The tiny fixture runs every loop in one chunk. Under a token chunk of 16 KiB the
    # long-sequence routes run instead: the global RoPE tables held as one frame's rows
    # (chunks.Periodic, sliced per chunk), merged Q/K/V sums over token chunks in a loop
    # that owns x, K/V-only layers and merged layers finishing their rows chunk by chunk,
    # frame and DINO blocks as K/V + query chunks. Same outputs, to float32 rounding.
    from rvggt_jax.ops import chunks
    from rvggt_jax.model import layers

    params, config = tiny
    cfg = config.with_compression(name)
    images = golden["images"]
    ref = preset_forward(name)[2]  # the default chunks (the preset test's compilation)
    monkeypatch.setattr(chunks, "TOKEN_CHUNK_BYTES", 16 * 1024)
    s, p = images.shape[1], 5 + (images.shape[3] // 14) * (images.shape[4] // 14)
    frame = layers.RopeTables.from_positions(jnp.zeros((1, p, 2), jnp.int32), cfg.head_dim, cfg.rope_freq)
    assert isinstance(layers.RopeTables.of_sequence(frame, s).cos, chunks.Periodic)
    assert chunks.row_chunks(s * p, 2 * cfg.embed_dim * 4) < s * p  # the merged sums in chunks
    out = jax.jit(lambda p, x: rvggt_forward(p, x, cfg))(params, images)  # a new function: traced anew
    for key in OUTPUTS:
        assert rel_err(out[key], ref[key]) <= 1e-5, key
