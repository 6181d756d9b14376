"""Checkpoints that are wrong inside: a NaN weight, bytes changed in a converted copy's
chunk, a converted folder missing its config.json or holding a truncated chunk, a
config.json that contradicts its tensors. Each is one clear error naming the tensor or
file, never a silent wrong answer nor a flood of tracebacks."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

from rvggt_jax import load_pretrained
from rvggt_jax.app import cli
from rvggt_jax.weights import integrity
from rvggt_jax.weights.checkpoint import save_orbax
from rvggt_jax.weights.errors import CheckpointError, CheckpointFileError
from rvggt_jax.weights.converter import flatten_params
from rvggt_jax.weights.integrity import DIGESTS_NAME, DigestMismatchError, NonFiniteWeightError, check_loaded
from tests.helpers import REPO, TINY

NAN_KEY = "aggregator.frame_blocks.3.mlp.fc1.bias"  # upstream key; our path is the same here


@pytest.fixture(scope="module")
def tiny_orbax(tmp_path_factory):
    """The tiny checkpoint converted once (numpy leaves) -> (folder, params)."""
    params, config = load_pretrained(TINY, device_put=False)
    return save_orbax(params, config, tmp_path_factory.mktemp("orbax") / "ckpt"), params


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def _cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err


def test_nan_weight_in_safetensors_is_refused_naming_it(tmp_path, capsys):
    tensors = load_file(TINY / "model.safetensors")
    tensors[NAN_KEY] = tensors[NAN_KEY].copy()
    tensors[NAN_KEY][3] = np.nan
    ck = tmp_path / "ck"
    ck.mkdir()
    save_file(tensors, ck / "model.safetensors")
    shutil.copy(TINY / "config.json", ck / "config.json")
    with pytest.raises(NonFiniteWeightError, match=f"{NAN_KEY}.*1 NaN/inf value"):
        load_pretrained(ck, device_put=False)
    code, err = _cli(capsys, "convert", ck, tmp_path / "out", "--quiet")
    assert code == 1 and err.startswith("rvggt: error:") and NAN_KEY in err.splitlines()[0]
    assert not (tmp_path / "out").exists()


def test_nan_weight_in_converted_copy_is_refused(tiny_orbax, tmp_path):
    _, params = tiny_orbax
    bad = {**params, "camera_head": {**params["camera_head"]}}
    leaf = next(k for k, v in bad["camera_head"].items() if isinstance(v, np.ndarray))
    bad["camera_head"][leaf] = np.full_like(params["camera_head"][leaf], np.inf)
    from rvggt_jax.config import VGGTConfig

    dst = save_orbax(bad, VGGTConfig.from_json(TINY / "config.json"), tmp_path / "nan")
    with pytest.raises(NonFiniteWeightError, match=f"camera_head.{leaf} holds"):
        load_pretrained(dst, device_put=False)


def _swap_chunk(ckpt, victim, donor):
    """Replace the chunk of parameter `victim` by `donor`'s (same shape, other numbers):
    valid zarr data, the wrong weights."""
    chunk = next(p for p in (ckpt / "params" / victim).iterdir() if not p.name.startswith("."))
    shutil.copy(ckpt / "params" / donor / chunk.name, chunk)


def test_changed_chunk_is_caught_by_its_digest(tiny_orbax, tmp_path):
    src, params = tiny_orbax
    victim, donor = "aggregator.frame_blocks.1.norm1.bias", "aggregator.frame_blocks.2.norm1.bias"
    a, b = (params["aggregator"]["frame_blocks"][i]["norm1"]["bias"] for i in ("1", "2"))
    assert not np.array_equal(a, b)
    ck = _copy(src, tmp_path / "ck")
    _swap_chunk(ck, victim, donor)
    with pytest.raises(DigestMismatchError, match=f"parameter {victim} differs"):
        load_pretrained(ck, device_put=False)


def test_digests_are_checked_once_per_copy(tiny_orbax, tmp_path, monkeypatch):
    """`check_loaded` (what every Orbax load runs) on the arrays as restored: hashed on the
    first load, not while the files stay as they were, again with verify=True or once a
    file changed; a copy without digests (older rvggt-jax) is not hashed and loads."""
    ck = _copy(tiny_orbax[0], tmp_path / "ck")
    flat = flatten_params(tiny_orbax[1])
    calls = []
    digest = integrity.array_digest
    monkeypatch.setattr(integrity, "array_digest", lambda x: calls.append(1) or digest(x))

    def hashed(**kw):
        n = len(calls)
        check_loaded(flat, ck, ck / "params", **kw)
        return len(calls) - n

    assert hashed() == len(flat) and hashed() == 0 and hashed(verify=True) == len(flat)
    assert hashed(complete=False) == 0
    chunk = ck / "params" / "depth_head.norm.bias" / "0"
    os.utime(chunk, ns=(chunk.stat().st_atime_ns, chunk.stat().st_mtime_ns + 10**9))
    wrong = {**flat, ("depth_head", "norm", "bias"): flat[("depth_head", "norm", "bias")] + 1}
    with pytest.raises(DigestMismatchError, match="depth_head.norm.bias"):
        check_loaded(wrong, ck, ck / "params")
    (ck / DIGESTS_NAME).unlink()
    assert hashed() == 0


def test_converted_folder_without_config_json(tiny_orbax, tmp_path, capsys):
    ck = _copy(tiny_orbax[0], tmp_path / "nocfg")
    (ck / "config.json").unlink()
    with pytest.raises(CheckpointFileError, match="has no config.json"):
        load_pretrained(ck, device_put=False)
    code, err = _cli(capsys, "reconstruct", REPO / "rvggt_jax/examples_data/images", "--weights", ck,
                     "--out", tmp_path / "out", "--quiet")
    lines = err.splitlines()
    assert code == 1 and lines[0].startswith("rvggt: error:") and "config.json" in lines[0]
    assert len(lines) == 1 and "does not match" not in err


def test_truncated_chunk_names_the_parameter(tiny_orbax, tmp_path):
    ck = _copy(tiny_orbax[0], tmp_path / "trunc")
    chunk = ck / "params" / "aggregator.camera_token" / "0.0.0.0"
    chunk.write_bytes(chunk.read_bytes()[:100])
    with pytest.raises(CheckpointFileError, match="parameter aggregator.camera_token cannot be read"):
        load_pretrained(ck, device_put=False)
    # onto the device, as the command loads it: one line, none of Orbax's stray tracebacks
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_PLATFORMS": "cpu", "RVGGT_CACHE_DIR": "off"}
    code = ("import sys; from rvggt_jax.app.model_runner import load_model\n"
            "from rvggt_jax.app.messages import CLIError\n"
            "try: load_model(sys.argv[1])\n"
            "except CLIError as e: print('rvggt: error:', e, file=sys.stderr); sys.exit(1)\n")
    r = subprocess.run([sys.executable, "-c", code, str(ck)], capture_output=True, text=True, timeout=300)
    # (Orbax's stragglers: one `RuntimeError: Event loop is closed` traceback each)
    assert r.returncode == 1 and "Event loop is closed" not in r.stderr, r.stderr[-2000:]
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("rvggt: error:")]
    assert len(errors) == 1 and "parameter aggregator.camera_token cannot be read" in errors[0], r.stderr[-2000:]


def test_config_json_contradicting_tensors_says_so_first(tiny_orbax, tmp_path, capsys):
    ck = _copy(tiny_orbax[0], tmp_path / "wide")
    cfg = json.loads((ck / "config.json").read_text())
    cfg["embed_dim"] = 2048
    (ck / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError) as ei:
        load_pretrained(ck)  # onto the device: refused before Orbax reads anything
    assert str(ei.value).splitlines()[0] == "config.json says embed_dim 2048; the tensors are 32 wide"
    code, err = _cli(capsys, "reconstruct", REPO / "rvggt_jax/examples_data/images", "--weights", ck,
                     "--out", tmp_path / "out", "--quiet")
    lines = err.splitlines()
    assert code == 1 and "config.json says embed_dim 2048; the tensors are 32 wide" in lines[0]
    assert len(lines) <= 40 and "more" in err, err
