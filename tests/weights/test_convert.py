"""Converter: upstream state-dict layout, conversion rules, checks, Orbax round trip, CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import ml_dtypes
import numpy as np
import pytest
from safetensors import safe_open
from safetensors.numpy import save_file

from rvggt_jax.weights import (
    RULES,
    CheckpointError,
    convert_state_dict,
    expected_param_paths,
    expected_param_shapes,
    find_rule,
    flatten_params,
    load_safetensors,
    upstream_state_dict_shapes,
)
from rvggt_jax.app.convert_command import main
from rvggt_jax.model.param_rules import apply_rule, converted_shapes, matching_rules
from rvggt_jax.weights.checkpoint import save_orbax
from rvggt_jax.weights.pretrained import load_pretrained
from rvggt_jax.config import VGGTConfig
from tests.helpers import DATA, TINY as TINY_DIR

MANIFEST = DATA / "vggt_1b_manifest.json"
TINY_ST = TINY_DIR / "model.safetensors"


@pytest.fixture(scope="module")
def manifest() -> dict[str, tuple[int, ...]]:
    with open(MANIFEST) as f:
        return {k: tuple(v[0]) for k, v in json.load(f).items()}


@pytest.fixture(scope="module")
def tiny_config() -> VGGTConfig:
    return VGGTConfig.from_json(TINY_DIR / "config.json")


@pytest.fixture(scope="module")
def tiny_raw() -> dict[str, np.ndarray]:
    with safe_open(str(TINY_ST), framework="numpy") as f:
        return {k: f.get_tensor(k) for k in f.keys()}


@pytest.fixture(scope="module")
def tiny_params(tiny_config):
    return load_safetensors(TINY_ST, tiny_config)


def _get(tree, dotted: str):
    for k in dotted.split("."):
        tree = tree[k]
    return tree


def _assert_trees_equal(a, b) -> None:
    fa, fb = flatten_params(a), flatten_params(b)
    assert set(fa) == set(fb)
    for k in fa:
        np.testing.assert_array_equal(np.asarray(fa[k]), np.asarray(fb[k]), err_msg=".".join(k))


# ---- upstream layout ----------------------------------------------------------------------


def test_shapes_equal_1b_manifest(manifest):
    shapes = upstream_state_dict_shapes(VGGTConfig())
    assert len(manifest) == 1797
    assert shapes == manifest


def test_shapes_equal_tiny_checkpoint(tiny_config):
    with safe_open(str(TINY_ST), framework="numpy") as f:
        tiny = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    assert upstream_state_dict_shapes(tiny_config) == tiny


def test_shapes_follow_enable_flags():
    c = VGGTConfig()
    keys = upstream_state_dict_shapes(dataclasses.replace(c, enable_track=False, enable_point=False))
    assert not any(k.startswith(("track_head.", "point_head.")) for k in keys)
    assert any(k.startswith("depth_head.") for k in keys)
    assert upstream_state_dict_shapes(c, skip_track=True) == upstream_state_dict_shapes(
        dataclasses.replace(c, enable_track=False)
    )
    no_conf = dataclasses.replace(c, track_head=dataclasses.replace(c.track_head, predict_conf=False))
    assert "track_head.tracker.conf_predictor.0.weight" not in upstream_state_dict_shapes(no_conf)


# ---- rule table on the 1B layout (shapes only) ----------------------------------------------


def test_every_1b_key_matches_exactly_one_rule(manifest):
    unmapped = [k for k in manifest if not matching_rules(k)]
    ambiguous = [k for k in manifest if len(matching_rules(k)) > 1]
    assert unmapped == [] and ambiguous == []
    used = {find_rule(k) for k in manifest}
    assert used == set(RULES), "rules that match no VGGT-1B key"


def test_1b_rules_map_to_expected_converted_shapes(manifest):
    flat = {}
    for key, shape in manifest.items():
        for path, s in converted_shapes(find_rule(key).kind, key, shape):
            assert path not in flat, f"{'.'.join(path)} written twice"
            flat[path] = s
    assert flat == expected_param_paths(VGGTConfig())
    expect = {
        "aggregator.frame_blocks.0.attn.q.kernel": (1024, 1024),
        "aggregator.frame_blocks.0.attn.v.bias": (1024,),
        "aggregator.global_blocks.23.attn.q_norm.scale": (64,),
        "aggregator.patch_embed.patch_embed.proj.kernel": (14, 14, 3, 1024),
        "aggregator.patch_embed.blocks.0.mlp.fc1.kernel": (1024, 4096),
        "aggregator.patch_embed.pos_embed": (1, 1370, 1024),
        "aggregator.frame_blocks.5.ls1.gamma": (1024,),
        "camera_head.poseLN_modulation.1.kernel": (2048, 6144),
        "camera_head.trunk.3.attn.k.kernel": (2048, 2048),
        "depth_head.projects.1.kernel": (1, 1, 2048, 512),
        "depth_head.resize_layers.0.kernel": (4, 4, 256, 256),
        "depth_head.scratch.layer2_rn.kernel": (3, 3, 512, 256),
        "depth_head.scratch.output_conv2.2.kernel": (1, 1, 32, 2),
        "point_head.scratch.output_conv2.2.kernel": (1, 1, 32, 4),
        "track_head.feature_extractor.scratch.output_conv1.kernel": (3, 3, 128, 128),
        "track_head.tracker.corr_mlp.fc1.kernel": (567, 384),
        "track_head.tracker.ffeat_norm.scale": (128,),
        "track_head.tracker.updateformer.time_blocks.5.attn.q.kernel": (384, 384),
        "track_head.tracker.updateformer.space_point2virtual_blocks.0.cross_attn.v.bias": (384,),
        "track_head.tracker.updateformer.space_virtual2point_blocks.5.cross_attn.out_proj.kernel": (384, 384),
        "track_head.tracker.updateformer.virual_tracks": (1, 64, 1, 384),
    }
    for dotted, shape in expect.items():
        assert flat[tuple(dotted.split("."))] == shape, dotted
    assert ("depth_head", "scratch", "layer1_rn", "bias") not in flat
    assert not any(p[-1] in ("weight", "qkv", "in_proj_weight") or "qkv" in p for p in flat)


def test_unknown_key_matches_no_rule():
    assert find_rule("aggregator.frame_blocks.0.attn.qkv.scale") is None
    assert find_rule("depth_head.scratch.output_conv2.1.weight") is None  # the ReLU
    assert find_rule("track_head.feature_extractor.scratch.output_conv2.0.weight") is None
    assert find_rule("camera_head.adaln_norm.weight") is None


# ---- tiny checkpoint conversion -------------------------------------------------------------


def test_tiny_converts_to_expected_shapes(tiny_params, tiny_config):
    want = expected_param_shapes(tiny_config)
    assert jax.tree.structure(tiny_params) == jax.tree.structure(want)
    for (path, got), (_, w) in zip(
        jax.tree_util.tree_leaves_with_path(tiny_params), jax.tree_util.tree_leaves_with_path(want)
    ):
        assert got.shape == w.shape, jax.tree_util.keystr(path)
        assert got.dtype == np.float32
        assert isinstance(w, jax.ShapeDtypeStruct)


def _assert_split_projection(sub, w, b):
    """A fused [3C, C] projection (rows [0:C], [C:2C], [2C:3C]) became Linears q, k, v
    with transposed kernels."""
    c = w.shape[1]
    for i, name in enumerate("qkv"):
        np.testing.assert_array_equal(sub[name]["kernel"], w[i * c : (i + 1) * c].T)
        np.testing.assert_array_equal(sub[name]["bias"], b[i * c : (i + 1) * c])


def test_tiny_layouts(tiny_params, tiny_raw):
    p, raw = tiny_params, tiny_raw
    # fused qkv -> q, k, v
    attn = _get(p, "aggregator.frame_blocks.3.attn")
    _assert_split_projection(attn, raw["aggregator.frame_blocks.3.attn.qkv.weight"],
                             raw["aggregator.frame_blocks.3.attn.qkv.bias"])
    assert "qkv" not in attn
    # nn.MultiheadAttention in_proj -> q, k, v
    ca = _get(p, "track_head.tracker.updateformer.space_point2virtual_blocks.1.cross_attn")
    _assert_split_projection(
        ca, raw["track_head.tracker.updateformer.space_point2virtual_blocks.1.cross_attn.in_proj_weight"],
        raw["track_head.tracker.updateformer.space_point2virtual_blocks.1.cross_attn.in_proj_bias"])
    np.testing.assert_array_equal(ca["out_proj"]["kernel"], raw[
        "track_head.tracker.updateformer.space_point2virtual_blocks.1.cross_attn.out_proj.weight"].T)
    # Linear: [out, in] -> [in, out]
    np.testing.assert_array_equal(
        _get(p, "camera_head.trunk.2.mlp.fc1.kernel"), raw["camera_head.trunk.2.mlp.fc1.weight"].T
    )
    np.testing.assert_array_equal(
        _get(p, "camera_head.poseLN_modulation.1.bias"), raw["camera_head.poseLN_modulation.1.bias"]
    )
    # norms: weight -> scale (LayerNorm, GroupNorm, qk-norm)
    norms = ("aggregator.patch_embed.norm", "track_head.tracker.ffeat_norm", "aggregator.global_blocks.0.attn.k_norm")
    for key in norms:
        np.testing.assert_array_equal(_get(p, key + ".scale"), raw[key + ".weight"])
        np.testing.assert_array_equal(_get(p, key + ".bias"), raw[key + ".bias"])
    # Conv2d [O, I, kh, kw] -> HWIO
    w = raw["depth_head.scratch.refinenet2.resConfUnit1.conv1.weight"]
    k = _get(p, "depth_head.scratch.refinenet2.resConfUnit1.conv1.kernel")
    assert k.shape == (w.shape[2], w.shape[3], w.shape[1], w.shape[0])
    np.testing.assert_array_equal(k[1, 2, 3, 4], w[4, 3, 1, 2])
    np.testing.assert_array_equal(k, w.transpose(2, 3, 1, 0))
    w = raw["aggregator.patch_embed.patch_embed.proj.weight"]
    np.testing.assert_array_equal(_get(p, "aggregator.patch_embed.patch_embed.proj.kernel"), w.transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(
        _get(p, "point_head.scratch.layer3_rn.kernel"), raw["point_head.scratch.layer3_rn.weight"].transpose(2, 3, 1, 0)
    )
    assert set(_get(p, "point_head.scratch.layer3_rn")) == {"kernel"}
    # ConvTranspose2d [I, O, kh, kw] -> [kh, kw, I, O]
    w = raw["track_head.feature_extractor.resize_layers.1.weight"]
    k = _get(p, "track_head.feature_extractor.resize_layers.1.kernel")
    np.testing.assert_array_equal(k, w.transpose(2, 3, 0, 1))
    np.testing.assert_array_equal(k[1, 0, 5, 7], w[5, 7, 1, 0])
    # raw parameters unchanged
    for key in ("aggregator.camera_token", "aggregator.patch_embed.pos_embed", "aggregator.frame_blocks.7.ls2.gamma",
                "track_head.tracker.query_ref_token", "track_head.tracker.updateformer.virual_tracks",
                "camera_head.empty_pose_tokens"):
        np.testing.assert_array_equal(_get(p, key), raw[key])
    # every leaf is an owning, C-contiguous float32 array
    for leaf in jax.tree.leaves(p):
        assert leaf.dtype == np.float32 and leaf.flags.c_contiguous


def test_convert_state_dict_mapping_equals_streaming(tiny_raw, tiny_config, tiny_params):
    _assert_trees_equal(convert_state_dict(tiny_raw, tiny_config), tiny_params)


def test_apply_rule_rejects_wrong_rank():
    with pytest.raises(ValueError, match="rank"):
        list(apply_rule("conv", "x.weight", np.zeros((3, 3))))


def test_low_precision_checkpoint_becomes_float32(tiny_raw, tiny_config):
    half = {k: v.astype(ml_dtypes.bfloat16 if i % 2 else np.float16) for i, (k, v) in enumerate(tiny_raw.items())}
    params = convert_state_dict(half, tiny_config)
    for leaf in jax.tree.leaves(params):
        assert leaf.dtype == np.float32
    key = "aggregator.frame_blocks.0.mlp.fc2"
    np.testing.assert_array_equal(_get(params, key + ".kernel"), half[key + ".weight"].astype(np.float32).T)


# ---- checks: one error naming every problem -------------------------------------------------


def _broken(tiny_raw):
    bad = dict(tiny_raw)
    del bad["camera_head.trunk.1.attn.qkv.weight"]  # missing
    bad["depth_head.scratch.output_conv3.weight"] = np.zeros((2, 2, 1, 1), np.float32)  # unexpected
    bad["aggregator.frame_blocks.2.mlp.fc1.weight"] = np.zeros((7, 32), np.float32)  # wrong shape
    bad["aggregator.camera_token"] = tiny_raw["aggregator.camera_token"].astype(np.int32)  # not float
    return bad


def _assert_names_all(err: CheckpointError) -> None:
    msg = str(err)
    assert isinstance(err, ValueError)
    assert [k for k, _ in err.missing] == ["camera_head.trunk.1.attn.qkv.weight"]
    assert err.unexpected == ["depth_head.scratch.output_conv3.weight"]
    assert [m[0] for m in err.mismatched] == ["aggregator.frame_blocks.2.mlp.fc1.weight"]
    assert [k for k, _ in err.bad_dtype] == ["aggregator.camera_token"]
    for name in ("camera_head.trunk.1.attn.qkv.weight", "depth_head.scratch.output_conv3.weight",
                 "aggregator.frame_blocks.2.mlp.fc1.weight", "(7, 32)", "(128, 32)", "aggregator.camera_token"):
        assert name in msg


def test_one_error_lists_missing_unexpected_and_misshaped(tiny_raw, tiny_config):
    with pytest.raises(CheckpointError) as ei:
        convert_state_dict(_broken(tiny_raw), tiny_config)
    _assert_names_all(ei.value)


def test_one_error_from_safetensors_file(tiny_raw, tiny_config, tmp_path):
    save_file(_broken(tiny_raw), str(tmp_path / "model.safetensors"))
    with pytest.raises(CheckpointError) as ei:
        load_safetensors(tmp_path / "model.safetensors", tiny_config)
    _assert_names_all(ei.value)
    from rvggt_jax.weights.checkpoint import ConfigInferredWarning

    with pytest.raises(CheckpointError), pytest.warns(ConfigInferredWarning):  # no config.json: inferred
        load_pretrained(tmp_path)


def test_tiny_checkpoint_against_1b_config_fails_with_shapes(tiny_raw):
    with pytest.raises(CheckpointError) as ei:
        convert_state_dict(tiny_raw, VGGTConfig())
    err = ei.value
    assert err.missing and err.mismatched and not err.unexpected


def test_skip_track_and_disabled_track(tiny_raw, tiny_config, tiny_params):
    params = convert_state_dict(tiny_raw, tiny_config, skip_track=True)
    assert "track_head" not in params
    assert set(params) == set(tiny_params) - {"track_head"}
    no_track_ckpt = {k: v for k, v in tiny_raw.items() if not k.startswith("track_head.")}
    _assert_trees_equal(convert_state_dict(no_track_ckpt, tiny_config, skip_track=True), params)
    # a config without the track head does not accept track tensors
    with pytest.raises(CheckpointError) as ei:
        convert_state_dict(tiny_raw, dataclasses.replace(tiny_config, enable_track=False))
    assert ei.value.unexpected and all(k.startswith("track_head.") for k in ei.value.unexpected)
    # ... nor does the full config accept their absence
    with pytest.raises(CheckpointError) as ei:
        convert_state_dict(no_track_ckpt, tiny_config)
    assert ei.value.missing and not ei.value.unexpected


# ---- Orbax / load_pretrained ----------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_orbax(tiny_params, tiny_config, tmp_path_factory) -> Path:
    return save_orbax(tiny_params, tiny_config, tmp_path_factory.mktemp("orbax") / "ckpt")


def test_orbax_round_trip(tiny_orbax, tiny_params, tiny_config):
    dst = tiny_orbax
    assert (dst / "config.json").is_file() and (dst / "params").is_dir()
    params, config = load_pretrained(dst)
    assert config == tiny_config
    assert jax.tree.structure(params) == jax.tree.structure(tiny_params)
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(params))
    _assert_trees_equal(params, tiny_params)
    params_np, _ = load_pretrained(dst / "params", device_put=False)
    assert all(isinstance(x, np.ndarray) for x in jax.tree.leaves(params_np))
    _assert_trees_equal(params_np, tiny_params)
    no_track, cfg = load_pretrained(dst, skip_track=True, device_put=False)
    assert "track_head" not in no_track and not cfg.enable_track
    _assert_trees_equal(no_track, {k: v for k, v in tiny_params.items() if k != "track_head"})
    with pytest.raises(FileExistsError):
        save_orbax(tiny_params, tiny_config, dst)


def test_save_orbax_checks_tree(tiny_params, tiny_config, tmp_path):
    bad = dict(tiny_params)
    del bad["camera_head"]
    with pytest.raises(CheckpointError, match="camera_head"):
        save_orbax(bad, tiny_config, tmp_path / "x")
    assert not (tmp_path / "x").exists()
    wrong_norm = {"scale": np.zeros(3), "bias": np.zeros(3)}
    bad = dict(tiny_params, depth_head=dict(tiny_params["depth_head"], norm=wrong_norm))
    with pytest.raises(CheckpointError, match="depth_head.norm.scale"):
        save_orbax(bad, tiny_config, tmp_path / "x")
    # a tree without the track head is saved with enable_track = False
    no_track = {k: v for k, v in tiny_params.items() if k != "track_head"}
    save_orbax(no_track, tiny_config, tmp_path / "nt")
    params, config = load_pretrained(tmp_path / "nt", device_put=False)
    assert not config.enable_track
    _assert_trees_equal(params, no_track)


def test_orbax_config_mismatch_is_reported(tiny_orbax, tmp_path):
    cfg = json.loads((tiny_orbax / "config.json").read_text())
    (tmp_path / "params").symlink_to(tiny_orbax / "params", target_is_directory=True)
    cfg["camera_head"]["trunk_depth"] = 3  # the tree differs
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError):
        load_pretrained(tmp_path, device_put=False)
    cfg["camera_head"]["trunk_depth"] = 4
    cfg["dpt_head"]["features"] = 8  # shapes differ
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="wrong shape"):
        load_pretrained(tmp_path, device_put=False)
    # (device_put=True raises CheckpointError too, but Orbax then leaves unawaited read
    # coroutines behind that warn when collected, in whatever test runs next)


def test_load_pretrained_safetensors_folder_and_file(tiny_params, tiny_config, tmp_path):
    params, config = load_pretrained(TINY_DIR, device_put=False)
    assert config == tiny_config
    _assert_trees_equal(params, tiny_params)
    params, config = load_pretrained(TINY_ST)
    assert config == tiny_config
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(params))
    _assert_trees_equal(params, tiny_params)
    # without a config.json beside it, the layout is inferred from the shapes, with a
    # warning naming what the shapes do not fix (head counts)
    from rvggt_jax.weights.checkpoint import ConfigInferredWarning

    lonely = tmp_path / "weights.safetensors"
    lonely.symlink_to(TINY_ST.absolute())
    with pytest.warns(ConfigInferredWarning, match="assumed: dino.num_heads=2"):
        params, config = load_pretrained(lonely, device_put=False)
    assert config.embed_dim == tiny_config.embed_dim and config.dpt_head == tiny_config.dpt_head
    _assert_trees_equal(params, tiny_params)


def test_load_pretrained_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_pretrained(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="neither"):
        load_pretrained(tmp_path)
    (tmp_path / "x.bin").write_bytes(b"")
    with pytest.raises(ValueError, match="safetensors"):
        load_pretrained(tmp_path / "x.bin")


# ---- CLI ------------------------------------------------------------------------------------


def test_cli(tiny_params, tiny_config, tmp_path, capsys):
    assert main([str(TINY_DIR), str(tmp_path / "out"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    params, config = load_pretrained(tmp_path / "out", device_put=False)
    assert config == tiny_config
    _assert_trees_equal(params, tiny_params)
    # existing destination needs --overwrite; explicit --config and --no-track
    assert main([str(TINY_ST), str(tmp_path / "out"), "--quiet"]) == 1
    assert "overwrite" in capsys.readouterr().err
    args = [str(TINY_ST), str(tmp_path / "out"), "--config", str(TINY_DIR / "config.json"), "--no-track", "-q"]
    assert main(args + ["--overwrite"]) == 0
    params, config = load_pretrained(tmp_path / "out", device_put=False)
    assert not config.enable_track and "track_head" not in params
    # a checkpoint that does not fit its config: exit status 1 and the keys named
    VGGTConfig().to_json(tmp_path / "1b.json")
    assert main([str(TINY_ST), str(tmp_path / "bad"), "--config", str(tmp_path / "1b.json"), "-q"]) == 1
    assert "aggregator.frame_blocks.0.attn.qkv.weight" in capsys.readouterr().err
    assert main([str(tmp_path / "missing"), str(tmp_path / "o2"), "-q"]) == 1
