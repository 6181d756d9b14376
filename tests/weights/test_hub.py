"""Checkpoints by Hugging Face repo id, offline only: a hub cache laid out as
huggingface_hub lays it out, holding the tiny test checkpoint (never the network)."""

import shutil

import numpy as np
import pytest

from tests.helpers import TINY
from tests.helpers.hub_cache import COMMIT, populate_hub_cache


@pytest.fixture
def offline_hub(tmp_path, monkeypatch):
    """HF_HUB_OFFLINE=1 with HF_HOME and the converted-weights folder in tmp_path."""
    import huggingface_hub.constants as c

    hf_home = tmp_path / "hf"
    monkeypatch.setenv("HF_HOME", str(hf_home))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("RVGGT_WEIGHTS_DIR", str(tmp_path / "converted"))
    # huggingface_hub reads its environment at import: point the module at ours too
    monkeypatch.setattr(c, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(c, "HF_HUB_CACHE", str(hf_home / "hub"))
    return hf_home


def _leaves(tree, prefix=()):
    for k, v in tree.items():
        if isinstance(v, dict):
            yield from _leaves(v, prefix + (k,))
        else:
            yield prefix + (k,), np.asarray(v)


def test_repo_id_loads_from_hub_cache_and_converts_once(offline_hub, tmp_path, monkeypatch):
    from rvggt_jax.weights import hub
    from rvggt_jax import load_pretrained

    populate_hub_cache(offline_hub, "test/tiny-vggt")
    params, config = load_pretrained("test/tiny-vggt", device_put=False)
    ref, ref_config = load_pretrained(TINY, device_put=False)
    assert config == ref_config
    ref_leaves = dict(_leaves(ref))
    got = dict(_leaves(params))
    assert got.keys() == ref_leaves.keys()
    for k in ref_leaves:
        np.testing.assert_array_equal(got[k], ref_leaves[k])
    conv = tmp_path / "converted" / "test--tiny-vggt" / COMMIT
    assert (conv / "params").is_dir() and (conv / "config.json").is_file()

    # the second time: no conversion, the Orbax copy is reused
    monkeypatch.setattr(hub, "_convert_to", lambda *a, **k: pytest.fail("converted twice"))
    assert hub.resolve_checkpoint("test/tiny-vggt") == conv
    # hub cache gone, still offline: the converted copy is used
    shutil.rmtree(offline_hub / "hub")
    assert hub.resolve_checkpoint("test/tiny-vggt") == conv


def test_offline_and_missing_says_what_is_missing(offline_hub):
    from rvggt_jax.weights.hub import HubError, resolve_checkpoint

    with pytest.raises(HubError) as e:
        resolve_checkpoint("facebook/VGGT-1B")
    msg = str(e.value)
    assert "model.safetensors" in msg and "facebook/VGGT-1B" in msg and "HF_HUB_OFFLINE" in msg
    assert str(offline_hub / "hub") in msg and "\n" not in msg


def test_repo_without_config_json_infers_layout(offline_hub):
    from rvggt_jax.weights.hub import resolve_checkpoint
    from rvggt_jax.weights.pretrained import load_pretrained

    populate_hub_cache(offline_hub, "test/no-config", files=("model.safetensors",))
    path = resolve_checkpoint("test/no-config")
    _, config = load_pretrained(path, device_put=False)
    assert config.embed_dim == 32 and config.depth == 24


def test_local_paths_win_over_repo_ids(tmp_path, monkeypatch):
    from rvggt_jax.weights.hub import is_repo_id

    assert is_repo_id("facebook/VGGT-1B") and is_repo_id("facebook/VGGT-1B-Commercial")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "facebook" / "VGGT-1B").mkdir(parents=True)
    assert not is_repo_id("facebook/VGGT-1B")  # an existing folder of that name
    assert not is_repo_id("weights/a/b") and not is_repo_id("/abs/path") and not is_repo_id("../x")
