"""`rvggt analyze` and `rvggt calibrate` on the bundled demo images with the tiny
random-weight model (in this process, 154 pixels wide: one compiled program per forward,
shared by the tests), the layer inputs they measure against upstream's, `--preset
path.json` (a file written from regime runs the very program regime runs, bit for bit),
and the analyze images in `rvggt view`'s panel."""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from PIL import Image

from rvggt_jax import diagnostics as D
from rvggt_jax.app import diagnostics_command as dc
from rvggt_jax.app.cli import main
from rvggt_jax.app.commands import TINY_WEIGHTS
from rvggt_jax.compression.config import make_compression
from rvggt_jax.compression.partition import Geometry
from tests.helpers import SAMPLE_IMAGES

M, SIZE = 32, "154"


@pytest.fixture(scope="module", autouse=True)
def _no_disk_cache():
    """No compilation cache on disk for these in-process runs."""
    old = os.environ.get("RVGGT_CACHE_DIR")
    os.environ["RVGGT_CACHE_DIR"] = "off"
    yield
    if old is None:
        os.environ.pop("RVGGT_CACHE_DIR", None)
    else:
        os.environ["RVGGT_CACHE_DIR"] = old


@pytest.fixture(scope="module")
def analyzed(tmp_path_factory):
    out = tmp_path_factory.mktemp("analyze") / "out"
    rc = main(["analyze", str(SAMPLE_IMAGES), "--weights", str(TINY_WEIGHTS), "--out", str(out), "--size", SIZE,
               "--m", str(M), "--quiet"])
    assert rc == 0
    return out, json.loads((out / dc.ANALYSIS_JSON).read_text())


def _scene():
    return dc._load_scene(SAMPLE_IMAGES, SimpleNamespace(max_frames=32, size=int(SIZE)))


def test_analyze_writes_the_maps_and_every_number(analyzed):
    out, doc = analyzed
    assert doc["frames"] == 3 and doc["image_hw"] == [112, 154] and doc["grid"] == [8, 11]
    assert "mean nothing" in doc["note"]
    r95 = np.array(doc["rank"]["r95"])
    assert r95.shape == (24, 2) and r95.min() >= 1 and r95.max() <= M and doc["rank"]["m"] == M
    np.testing.assert_allclose(doc["rank"]["normalised"], r95 / M, rtol=1e-5)
    np.testing.assert_allclose(doc["rank"]["profile"], (r95 / M).mean(1), rtol=1e-5)
    spectra = np.array(doc["rank"]["spectra"])
    assert spectra.shape == (24, 2, M) and np.all(np.diff(spectra, axis=-1) <= 1e-6) and spectra.min() >= 0
    # each head's r95 is the one its spectrum gives
    assert np.array_equal(np.asarray(D.r95_of_spectrum(spectra.astype(np.float32))), r95)
    # Psi is the saliency the model computes for these images
    from rvggt_jax.model.patch_embed import patch_embed_tokens
    from rvggt_jax.weights.checkpoint import load_checkpoint

    images, _ = _scene()
    params, config = load_checkpoint(str(TINY_WEIGHTS), skip_track=True, progress=False)
    psi = np.asarray(jax.jit(lambda p, x: patch_embed_tokens(p, x, config)[2])(
        params["aggregator"]["patch_embed"], images[None]))[0]
    np.testing.assert_allclose(doc["saliency"]["psi"], psi, rtol=2e-5, atol=1e-9)
    top = [sorted(np.argsort(-psi[f], kind="stable")[:8].tolist()) for f in (1, 2)]
    assert doc["saliency"]["protected"] == [[], *top]
    # K/V: regime's two tiles, coverage as the closed-form-tested function says
    geom = Geometry(3, 8, 11, 5)
    assert sorted(tuple(k["tile"]) for k in doc["kv"]) == [(3, 2), (5, 3)]
    for k in doc["kv"]:
        assert k["union_coverage"] == pytest.approx(D.union_coverage(geom, tuple(k["tile"]), True, [1, 2])[1])
    bands = {b["band"]: (b["layer"], b["layers"]) for b in doc["merge_bands"]}
    assert bands == {"shallow": (0, list(range(10))), "middle": (10, list(range(10, 18))),
                     "deep": (18, list(range(18, 24)))}
    assert all(0 < f <= 1 for b in doc["merge_bands"] for f in b["in_groups_fraction_per_frame"][1:])
    assert doc["cost"]["predicted_speedup"] > 1
    assert {"rank_profile.png", "saliency.png", "kv_t3k2.png", "kv_t5k3.png", "groups_shallow.png",
            "groups_middle.png", "groups_deep.png"} <= set(doc["files"])
    for name in doc["files"]:
        with Image.open(out / name) as im:
            assert im.format == "PNG" and min(im.size) > 50


def test_layer_inputs_are_the_global_blocks_inputs(analyzed):
    """The dense layer inputs rank_profile measures are upstream's frame-block outputs of
    every layer (the golden aggregator layers of the tiny fixture: the first half of each
    [B, S, P, 2C] layer). Same shapes and config as analyze's: no new compile."""
    from safetensors.numpy import load_file

    from rvggt_jax.weights.checkpoint import load_checkpoint
    from tests.helpers import TINY

    golden = load_file(TINY / "io.safetensors")
    params, config = load_checkpoint(str(TINY), skip_track=True, progress=False)  # as analyze loads
    compiled = D.layer_inputs._cache_size()
    x, psi = D.layer_inputs(params, jax.numpy.asarray(golden["images"]), config.with_compression("dense"),
                            tuple(range(24)))
    assert D.layer_inputs._cache_size() == compiled
    want = np.stack([golden[f"aggregated_{i:02d}"][..., :32].reshape(1, -1, 32) for i in range(24)])
    np.testing.assert_allclose(np.asarray(x), want, rtol=2e-4, atol=2e-4)
    np.testing.assert_allclose(np.asarray(psi), golden["dino_cls_saliency"], rtol=1e-4, atol=1e-6)


def test_calibrate_from_analyze_json_and_from_images(analyzed, tmp_path, capsys):
    out, doc = analyzed
    assert main(["calibrate", str(out / dc.ANALYSIS_JSON), "--out", str(tmp_path / "a")]) == 0
    said = capsys.readouterr()
    assert "predicted aggregator speedup" in said.out and "mean nothing" in said.err
    comp = D.load_preset(tmp_path / "a" / dc.PRESET_JSON, 24)
    assert comp == D.propose(doc["rank"]["profile"])[0]
    cal = json.loads((tmp_path / "a" / dc.CALIBRATION_JSON).read_text())
    sp = cal["predicted_speedup"]
    assert sp["frames"] == 3 and math.isfinite(sp["ratio"]) and sp["ratio"] == pytest.approx(
        sp["speedup"] / sp["regime_speedup"])
    assert cal["predicted_speedup_vggt1b_100x392x518"]["regime_speedup"] > 2
    # measuring the images again (same m, seed, size) gives the same profile, so the same preset
    assert main(["calibrate", str(SAMPLE_IMAGES), "--weights", str(TINY_WEIGHTS), "--out", str(tmp_path / "b"),
                 "--size", SIZE, "--m", str(M), "--quiet"]) == 0
    assert D.load_preset(tmp_path / "b" / dc.PRESET_JSON) == comp
    # the file is a preset --preset accepts
    from rvggt_jax.app.options import ReconstructOptions

    ReconstructOptions(preset=str(tmp_path / "a" / dc.PRESET_JSON)).check()


def test_a_preset_file_written_from_regime_runs_identically(analyzed, tmp_path):
    """load(save(regime)) == regime, so the forward under it is regime's compiled program
    (a jit cache hit, no new compile) and its outputs are bitwise regime's."""
    from rvggt_jax.app.model_runner import model_for as _model_for
    from rvggt_jax.app.options import ReconstructOptions

    regime = make_compression("regime", 24)
    path = D.save_preset(regime, tmp_path / "regime.json")
    loaded = D.load_preset(path, 24)
    assert loaded == regime and hash(loaded) == hash(regime) and loaded is not regime
    params, by_name = _model_for(TINY_WEIGHTS, "tiny", ReconstructOptions(preset="regime"))
    _, by_file = _model_for(TINY_WEIGHTS, "tiny", ReconstructOptions(preset=str(path)))
    assert by_file == by_name and by_file.compression == regime
    images, _ = _scene()
    layers = dc.preset_forward_layers(regime, Geometry(3, 8, 11, 5))  # what analyze ran
    by_name_out = D.layer_inputs(params, images[None], by_name, layers, with_output=True)
    compiled = D.layer_inputs._cache_size()
    by_file_out = D.layer_inputs(params, images[None], by_file, layers, with_output=True)
    assert D.layer_inputs._cache_size() == compiled
    # the layer inputs, Psi and the aggregator's output [B, S, P, 2C] the heads read
    for a, b in zip(by_file_out, by_name_out):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    assert by_file_out[2].shape == (1, 3, 5 + 8 * 11, 64) and np.isfinite(np.asarray(by_file_out[2])).all()


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"rank": {}}))
    cases = [
        (["reconstruct", str(SAMPLE_IMAGES), "--weights", str(TINY_WEIGHTS), "--out", str(tmp_path / "r"),
          "--preset", str(tmp_path / "missing.json")], "preset file not found"),
        (["analyze", str(SAMPLE_IMAGES), "--weights", str(TINY_WEIGHTS), "--out", str(tmp_path / "a"),
          "--preset", str(bad)], "bad.json is not valid JSON"),
        (["analyze", str(tmp_path / "nope"), "--weights", str(TINY_WEIGHTS), "--out", str(tmp_path / "a")],
         "image folder not found"),
        (["analyze", str(SAMPLE_IMAGES), "--weights", str(TINY_WEIGHTS), "--out", str(tmp_path / "a"),
          "--size", "100"], "--size must be a positive multiple of 14"),
        (["calibrate", str(SAMPLE_IMAGES), "--weights", str(TINY_WEIGHTS), "--out", str(tmp_path / "c"),
          "--size", "1000006"], "of at most 1022; got 1000006"),  # XLA used to abort the process
        (["calibrate", str(other), "--out", str(tmp_path / "c")], "not a diagnostics.json"),
        (["calibrate", str(SAMPLE_IMAGES), "--out", str(tmp_path / "c")], "--weights is needed"),
        (["calibrate", str(tmp_path / "x.json"), "--out", str(tmp_path / "c")], "input not found"),
    ]
    for argv, message in cases:
        assert main(argv) != 0, argv
        err = capsys.readouterr().err
        assert f"rvggt: error: " in err and message in err.split("rvggt: error: ")[1], (argv, err)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_view_shows_the_analyze_images(analyzed, tmp_path):
    from rvggt_jax.app.viewer import diagnostics_images, start
    from rvggt_jax.io.cameras import write_cameras_json
    from rvggt_jax.io.ply import write_ply

    out, doc = analyzed
    rec = tmp_path / "rec"
    rec.mkdir()
    pts = np.random.default_rng(0).uniform(-1, 1, (100, 3)) + [0, 0, 4]
    write_ply(rec / "points.ply", pts, np.full((100, 3), 200, np.uint8))
    ext = np.tile(np.hstack([np.eye(3), np.zeros((3, 1))]), (2, 1, 1))
    k = np.tile(np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]), (2, 1, 1))
    write_cameras_json(rec / "cameras.json", ["a.jpg", "b.jpg"], ext, k, [(100, 80)] * 2)
    assert diagnostics_images(rec) == []
    shutil.copytree(out, rec / "diagnostics")
    pngs = [n for n in doc["files"] if n.endswith(".png")]
    assert [p.name for p in diagnostics_images(rec)] == pngs
    server, viewer = start(rec, port=_free_port())
    try:
        assert len(viewer.diagnostics) == len(pngs)
        assert all(type(h).__name__ == "GuiImageHandle" for h in viewer.diagnostics)
    finally:
        server.stop()
