"""Memory of long sequences, from XLA's own plan of the compiled forward (nothing runs).

At 200 frames of 168 x 224 (39,400 tokens, a 24-layer width-256 model) attention over the
sequence dominates: the compressed path must need no more than dense (it was 3.7x
at 100 frames of VGGT-1B before its layers ran as scanned bands over chunked, in-place
blocks), and bfloat16 must need clearly less than float32."""

import dataclasses

import jax
import jax.numpy as jnp
import pytest

import rvggt_jax
from rvggt_jax.errors import InputError
from tests.helpers.long_sequence import BASE, H, S, W


def _layers_kept(cfg) -> tuple[list[int], dict]:
    """(the layers `cfg`'s forward keeps whole, {layer: width} of those kept as their
    heads' projections)."""
    from rvggt_jax.model.forward import _head_projections
    from rvggt_jax.planning.memory import abstract_params

    both = {"depth_head": cfg.enable_depth, "point_head": cfg.enable_point}
    proj = _head_projections(abstract_params(cfg), cfg, cfg.token_grid((H, W)), False, both)
    return sorted(set(cfg.needed_layers(False)) - set(proj)), {i: p.width for i, p in proj.items()}


def test_the_long_sequence_keeps_vggt_1bs_layers():
    # (so the kept-buffer checks below see VGGT-1B's buffers: 17 and 23 whole, 4 and 11
    # as the depth and point heads' projections)
    assert _layers_kept(BASE) == ([17, 23], {4: 128, 11: 256})


@pytest.fixture(scope="module")
def plans():
    return {(preset, dtype): rvggt_jax.memory_report(BASE.with_compression(preset), S, H, W, dtype=dtype)
            for preset in ("dense", "regime") for dtype in ("float32", "bfloat16")}


def test_regime_needs_no_more_memory_than_dense(plans):
    # float32: at most 1.1x dense (the target; measured 0.95x here). bfloat16: the merge
    # sums stay float32 while dense's activations halve, measured 1.14x here (1.0x at
    # 1000 frames of VGGT-1B, docs/benchmarks.md); 1.2x guards against regressions.
    for dtype, bound in (("float32", 1.1), ("bfloat16", 1.2)):
        dense, regime = plans["dense", dtype], plans["regime", dtype]
        assert regime.total_bytes <= bound * dense.total_bytes, (dtype, str(dense), str(regime))


def test_bfloat16_needs_less_than_float32(plans):
    # all but the outputs, which are float32 in both (the heads compute in float32): they
    # are a fifth of the float32 plan here, since the kept layers 4 and 11 are their
    # heads' projections (bfloat16 totals 0.81x float32's)
    for preset in ("dense", "regime"):
        f32, bf16 = plans[preset, "float32"], plans[preset, "bfloat16"]
        assert bf16.output_bytes == f32.output_bytes
        assert bf16.total_bytes - bf16.output_bytes < 0.8 * (f32.total_bytes - f32.output_bytes), (str(f32), str(bf16))
        assert bf16.param_dtype == "bfloat16" and bf16.argument_bytes < f32.argument_bytes


def test_report_is_consistent(plans):
    rep = plans["regime", "bfloat16"]
    assert rep.total_bytes == rep.argument_bytes + rep.output_bytes + rep.temp_bytes - rep.alias_bytes
    assert (rep.frames, rep.height, rep.width, rep.preset, rep.dtype) == (S, H, W, "regime", "bfloat16")
    assert "GB" in str(rep) and "200 frames" in str(rep)
    # the outputs: depth, points and their confidences in float32; no copy of the images
    # (with_outputs(images=True) asks for it)
    per_pixel = S * H * W * 4
    assert per_pixel * (1 + 1 + 3 + 1) <= rep.output_bytes < per_pixel * (1 + 1 + 3 + 1 + 3)


def test_donated_float32_images_hold_the_point_map(plans):
    # XLA may reuse the donated images' buffer once the patch embed has read them: the
    # float32 point map [S, H, W, 3] has their size and is written there. A plain jit
    # holds them to the end (XLA:TPU refused float32 images at 1000 frames on a v6e so).
    from tests.helpers.micro import micro_config

    images = S * 3 * H * W * 4
    for dtype in ("float32", "bfloat16"):
        rep = plans["regime", dtype]
        assert rep.images_donated and rep.alias_bytes == images, str(rep)
    cfg = micro_config(enable_depth=False, enable_track=False)
    kept, donated = (rvggt_jax.memory_report(cfg, 2, 28, 28, donate_images=d) for d in (False, True))
    assert not kept.images_donated and kept.alias_bytes == 0
    assert donated.alias_bytes == 2 * 3 * 28 * 28 * 4
    # (XLA's temporaries move by a few hundred bytes between the two programs)
    assert abs(kept.total_bytes - donated.total_bytes - donated.alias_bytes) <= 0.05 * donated.alias_bytes


@pytest.mark.parametrize("frames, height, width", [(0, 168, 224), (4, 170, 224), (4, 168, -14)])
def test_bad_sizes_are_named(frames, height, width):
    with pytest.raises(InputError):
        rvggt_jax.memory_report(dataclasses.replace(BASE), frames, height, width)


def test_kept_layers_are_never_converted_whole(plans):
    # bfloat16 kept layers are held as bits (bits.HalfBuffer) and the heads slice them per
    # group of frames: no op of the compiled forward may convert a whole kept buffer [K,
    # B, S, P, C] (a loop-invariant view XLA hoists out of the heads' loop: 8.5 GB per
    # buffer at 1000 frames of VGGT-1B, before HalfBuffer)
    import math
    import re

    cfg = BASE.with_compression("dense")
    keep, projected = _layers_kept(cfg)
    whole = len(keep) * S * (cfg.patch_start_idx + (H // 14) * (W // 14)) * cfg.embed_dim
    # (and no whole projection: [B*S, h*w, F], bits too)
    wholes = {whole} | {S * (H // 14) * (W // 14) * f for f in projected.values()}
    text = plans["dense", "bfloat16"].compiled.as_text()
    converts = re.findall(r"= \w+\[([\d,]*)\]\{[\d,]*\} (?:bitcast-)?convert\(", text)
    assert converts  # the pattern still matches XLA's text
    shapes = [[int(d) for d in dims.split(",") if d] for dims in converts]
    # (minus the MLP's hidden chunks, [frames, P, 4C]: 100 frames of them hold as many
    # values as the two kept slots here)
    sizes = [math.prod(dims) for dims in shapes if not dims or dims[-1] != 4 * cfg.embed_dim]
    assert not wholes & set(sizes), f"a whole kept buffer ({wholes & set(sizes)} values) is converted"


def test_last_layer_global_half_has_no_slot(plans):
    # The kept layers' halves are [K, B, S, P, C] buffers (16-bit: as uint16 bits), but
    # the last layer's global half is the final residual stream: the global buffer holds
    # K - 1 slots (a slot is 2.1 GB at 1000 frames of VGGT-1B in bfloat16).
    import re

    cfg = BASE.with_compression("dense")
    keep = len(_layers_kept(cfg)[0])
    assert cfg.depth - 1 in cfg.needed_layers(False)
    p = cfg.patch_start_idx + (H // 14) * (W // 14)
    text = plans["dense", "bfloat16"].compiled.as_text()
    # (one slot's worth, [1, ...], is what each layer writes; here the global buffer is
    # one slot too: keep = 2)
    slots = {int(k) for k in re.findall(rf"u16\[(\d+),1,{S},{p},{cfg.embed_dim}\]", text)} - {1}
    assert slots == {keep, keep - 1} - {1}, slots
    # the projections' buffers, as bits: [B*S, h*w, F]
    assert re.search(rf"u16\[{S},{(H // 14) * (W // 14)},128\]", text)


@pytest.mark.parametrize("fn", ["map_tokens", "map_tokens_through"])
def test_16bit_chunk_outputs_are_written_in_place(fn):
    # A bfloat16 result stitched from chunks whose last chunk overlaps the one before (n
    # not a multiple of the chunk) is written in place: reading the written rows back made
    # XLA:CPU copy the whole result in every step (chunks._chunk_loop), a temporary as large as
    # the result.
    import jax
    import jax.numpy as jnp

    from rvggt_jax.ops import chunks

    n, c, rows = 10_001, 256, 1_024  # 10 chunks of 1,008 rows: the last overlaps
    x = jax.ShapeDtypeStruct((1, n, c), jnp.float32)

    def half(xc):
        return (xc * 2).astype(jnp.bfloat16)

    def run(x):
        if fn == "map_tokens":
            return chunks.map_tokens(half, (x,), rows=rows)
        return chunks.map_tokens_through(half, x, rows=rows)  # (x too: an argument it owns is copied)

    compiled = jax.jit(run).lower(x).compile()
    result_bytes = n * c * 2
    assert compiled.memory_analysis().output_size_in_bytes >= result_bytes
    assert compiled.memory_analysis().temp_size_in_bytes < result_bytes / 4


def test_sequence_rope_tables_are_never_formed_whole(plans, monkeypatch):
    # The global blocks' RoPE tables are held as one frame's rows (chunks.Periodic): a loop
    # over token chunks takes each chunk's rows mod the frame, a loop run in one chunk
    # tiles them in its body, where XLA fuses the tiling into the RoPE product. So no
    # array of the compiled forward has a row per token of the sequence and the head
    # dimension [1, S*P, 1, D] (2 x 266 MB at 1000 frames of VGGT-1B): neither in the
    # suite's 200-frame plan (every loop in one chunk) nor in a 22-frame plan with a 1 MiB
    # chunk (the chunked loops). The pattern itself is checked on a program that does
    # form such an array. (22 frames: a cached trace of the suite's frame count would not
    # see the patch. That plan has the camera head only: the depth and point heads hold
    # no RoPE table, and without them the aggregator runs the same runs of global plans,
    # only not cut at the layers they read; about two thirds of the compile.)
    import re

    from rvggt_jax.model import layers
    from rvggt_jax.ops import chunks

    cfg = BASE.with_compression("regime")
    per_frame = cfg.patch_start_idx + (H // 14) * (W // 14)

    def has_tables(text, frames):
        return re.search(rf"f32\[1,{frames * per_frame},1,{cfg.head_dim}\]", text) is not None

    frame = layers.RopeTables.from_positions(jnp.zeros((1, per_frame, 2), jnp.int32), cfg.head_dim, cfg.rope_freq)
    tiled = jax.jit(lambda c: chunks.Periodic(c, S * per_frame).whole()).lower(frame.cos).compile()
    assert has_tables(tiled.as_text(), S)
    assert not has_tables(plans["regime", "float32"].compiled.as_text(), S)
    monkeypatch.setattr(chunks, "TOKEN_CHUNK_BYTES", 2**20)
    assert 22 * per_frame * cfg.head_dim * 4 > chunks.TOKEN_CHUNK_BYTES
    camera_only = dataclasses.replace(cfg, enable_depth=False, enable_point=False)
    assert not has_tables(rvggt_jax.memory_report(camera_only, 22, H, W).compiled.as_text(), 22)


def _written_constants(text: str, min_bytes: int = 2**20) -> list[str]:
    """The fusions of a compiled program's text that write one scalar constant out to an
    array of at least `min_bytes` (float32)."""
    import re

    consts = set(re.findall(r"%(constant[\w.]*) = f32\[\] constant\(", text))
    found = []
    for m in re.finditer(r"%([\w.\-]+) = f32\[([\d,]+)\]\S* fusion\(%([\w.\-]+)\), kind=kLoop", text):
        size = 4
        for d in m.group(2).split(","):
            size *= int(d)
        if m.group(3) in consts and size >= min_bytes:
            found.append(m.group(0))
    return found


def test_no_trigonometry_or_written_constants_in_the_forward(plans):
    # The RoPE tables are constants of the program (`aggregator.rope_tables`): computed in
    # it, XLA:CPU fused cos and sin into their consumers outside the layer loops, taking
    # them again for every token (this plan of `regime` had them too). No scalar constant
    # is written out as a large array: GELU's constants, as scalars, were merged across
    # the blocks outside a loop with one MLP shape and written out in full for their
    # YNNPACK fusions (the speed layout at 64 frames, docs/history/cpu_speed.md; not this plan,
    # where the check guards against new cases). Both checks also run on programs that
    # have what they look for.
    import re

    from rvggt_jax.model import layers

    trig = re.compile(r" (cosine|sine)\(")
    for preset in ("dense", "regime"):
        text = plans[preset, "float32"].compiled.as_text()
        assert trig.search(text) is None, preset
        assert _written_constants(text) == [], preset
    cfg = BASE.with_compression("regime")
    traced = jax.jit(lambda pos: layers.RopeTables.from_positions(pos, cfg.head_dim, cfg.rope_freq).cos)
    assert trig.search(traced.lower(jnp.zeros((1, 8, 2), jnp.int32)).compile().as_text())

    def attend(q, k, v):  # (XLA:CPU writes out softmax's divisor constant, [64, 1, 197], for both)
        w = jax.nn.softmax(jnp.einsum("bqhd,bkhd->bhqk", q, k), axis=-1)
        return jnp.einsum("bhqk,bkhd->bqhd", w, v)

    x = jax.ShapeDtypeStruct((64, 197, 1, 64), jnp.float32)
    two = jax.jit(lambda q, k, v: attend(attend(q, k, v) + q, k, v)).lower(x, x, x).compile().as_text()
    assert _written_constants(two, min_bytes=64 * 197 * 4)
