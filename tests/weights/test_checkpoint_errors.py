"""Checkpoints as users have them: a lone model.safetensors (no config.json), a truncated
download, a PyTorch .pt; and the one error format (`rvggt: error:` + indented details)."""

import json
import shutil
import warnings

import pytest

from rvggt_jax.app import cli
from rvggt_jax.weights.checkpoint import CheckpointFileError, ConfigInferredWarning, config_for_safetensors
from rvggt_jax.config import VGGTConfig
from tests.helpers import TINY


def run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_lone_safetensors_layout_inferred(tmp_path):
    st = tmp_path / "model.safetensors"
    shutil.copy(TINY / "model.safetensors", st)  # no config.json beside it
    with pytest.warns(ConfigInferredWarning, match="camera_head.num_heads") as rec:
        config = config_for_safetensors(st)
    msg = str(rec[0].message)
    assert "\n" not in msg and str(st) in msg and "config.json" in msg
    want = VGGTConfig.from_json(TINY / "config.json")
    for f in ("embed_dim", "depth", "num_heads", "num_register_tokens", "dino", "dpt_head", "track_head"):
        assert getattr(config, f) == getattr(want, f), f
    from rvggt_jax import load_pretrained

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigInferredWarning)
        params, cfg = load_pretrained(st, device_put=False)  # loads: no mismatch flood
    assert cfg.embed_dim == 32 and "track_head" in params


def test_1b_shapes_need_no_config():
    from rvggt_jax.weights.infer import infer_config
    from rvggt_jax.model.params import upstream_state_dict_shapes

    config, assumed = infer_config(upstream_state_dict_shapes(VGGTConfig()))
    assert config == VGGTConfig() and assumed == []


def test_convert_truncated_file_names_it(tmp_path, capsys):
    st = tmp_path / "model.safetensors"
    data = (TINY / "model.safetensors").read_bytes()
    for cut in (100, len(data) // 2):
        st.write_bytes(data[:cut])
        code, _, err = run(capsys, "convert", st, tmp_path / "dst", "--quiet")
        assert code == 1
        first = err.splitlines()[0]
        assert first.startswith("rvggt: error:") and str(st) in first and "truncated or corrupt" in first
        assert "Traceback" not in err
    from rvggt_jax import load_pretrained

    with pytest.raises(CheckpointFileError, match="truncated"):
        load_pretrained(st, device_put=False)


def test_convert_mismatch_details_indented(tmp_path, capsys):
    ck = tmp_path / "ck"
    ck.mkdir()
    shutil.copy(TINY / "model.safetensors", ck / "model.safetensors")
    cfg = json.loads((TINY / "config.json").read_text())
    cfg["embed_dim"] = 64
    (ck / "config.json").write_text(json.dumps(cfg))
    code, _, err = run(capsys, "convert", ck, tmp_path / "dst", "--quiet")
    lines = err.splitlines()
    # the plain reason first, then the counts and (at most 10 per kind) the tensors
    assert code == 1 and lines[0] == "rvggt: error: config.json says embed_dim 64; the tensors are 32 wide"
    assert lines[1].startswith("  checkpoint does not match")
    assert 3 < len(lines) < 60 and all(ln.startswith("  ") for ln in lines[1:])


def test_pt_is_not_advertised_and_refused_clearly(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert ".pt" not in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["convert", "--help"])
    assert ".pt" not in capsys.readouterr().out
    pt = tmp_path / "model.pt"
    pt.write_bytes(b"PK\x03\x04 not really")
    code, _, err = run(capsys, "convert", pt, tmp_path / "dst")
    assert code == 1 and err.startswith("rvggt: error:") and "model.pt" in err and "safetensors" in err
    code, _, err = run(capsys, "convert")  # usage errors: one line too
    assert code == 2 and len(err.strip().splitlines()) == 1 and err.startswith("rvggt: error:")


def test_version(capsys):
    import rvggt_jax

    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and rvggt_jax.__version__ in capsys.readouterr().out
