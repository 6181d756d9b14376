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


def _same_as_tiny(params):
    ref, _ = __import__("rvggt_jax").load_pretrained(TINY, device_put=False)
    want, got = dict(_leaves(ref)), dict(_leaves(params))
    assert got.keys() == want.keys()
    for k in want:
        np.testing.assert_array_equal(got[k], want[k])


def test_two_concurrent_first_runs_both_succeed(offline_hub, monkeypatch):
    """Two runs start at once on the same repo id (threads here; the lock is per open
    file, so it serialises threads as it does processes): one converts, the other waits
    and uses its copy; both read complete data. (Before: both converted, and the second
    deleted the first one's folder while the first was loading it.) The cache also holds
    what killed runs left: a copy without its completion marker and a temporary sibling;
    both are detected and redone."""
    import threading
    import time

    from rvggt_jax import load_pretrained
    from rvggt_jax.weights import converter, hub

    populate_hub_cache(offline_hub, "test/tiny-vggt")
    dst = hub.converted_root() / "test--tiny-vggt" / COMMIT
    (dst / "params").mkdir(parents=True)
    (dst / "params" / "half-written").write_text("x")
    stale = dst.parent / f".{COMMIT}.tmp-killed"
    (stale / "params").mkdir(parents=True)

    conversions = []
    real = converter.load_safetensors

    def slow_load(*a, **k):  # long enough that the runs overlap
        conversions.append(threading.get_ident())
        time.sleep(0.5)
        return real(*a, **k)

    monkeypatch.setattr(converter, "load_safetensors", slow_load)
    start = threading.Barrier(2)
    results, errors = [], []

    def run():
        start.wait()
        try:
            results.append(load_pretrained("test/tiny-vggt", device_put=False)[0])
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=run) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert len(conversions) == 1
    assert len(results) == 2
    for params in results:
        _same_as_tiny(params)
    assert (dst / ".complete").is_file() and not (dst / "params" / "half-written").exists()
    assert not stale.exists()


def test_a_finished_copy_is_never_replaced(tmp_path, monkeypatch):
    """A run that finishes converting after another one published: its copy is
    discarded, the published folder (which the other run may be reading) stays.
    (Before: the published folder was deleted and replaced.) The conversion itself is
    faked: only where its result goes is tested."""
    from rvggt_jax.weights import checkpoint, converter, hub

    monkeypatch.setattr(checkpoint, "config_for_safetensors", lambda st, cfg: None)
    monkeypatch.setattr(converter, "load_safetensors", lambda *a, **k: {})
    monkeypatch.setattr(checkpoint, "save_orbax",
                        lambda params, config, d, overwrite: (d / "params").mkdir() or d)
    dst = tmp_path / "test--tiny" / COMMIT
    (dst / "params").mkdir(parents=True)
    (dst / "params" / "theirs").write_text("published")
    (dst / ".complete").write_text("")
    hub._convert_to(tmp_path / "model.safetensors", None, dst, False)  # the slower run, done
    assert (dst / "params" / "theirs").read_text() == "published"
    assert sorted(p.name for p in dst.parent.iterdir()) == [COMMIT]


def test_publish_dir_race_one_wins_the_other_uses_it(tmp_path):
    """`publish_dir` without any lock: several finished copies race to the same place;
    every caller gets the one complete folder, and no temporary is left."""
    import threading

    from rvggt_jax.weights.hub import publish_dir

    dst = tmp_path / "copy"
    tmps = []
    for i in range(4):
        t = tmp_path / f".copy.tmp-{i}"
        t.mkdir()
        (t / "data").write_text(str(i))
        (t / ".complete").write_text("")
        tmps.append(t)
    start = threading.Barrier(len(tmps))
    got = []

    def run(t):
        start.wait()
        got.append(publish_dir(t, dst))

    threads = [threading.Thread(target=run, args=(t,)) for t in tmps]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert got == [dst] * 4 and (dst / ".complete").is_file() and (dst / "data").read_text() in "0123"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy"]


def test_unreachable_hub_fails_fast_with_the_offline_message(tmp_path):
    """HF_ENDPOINT at a closed local port (never the network): one quick probe, then the
    message, instead of ~25 s of huggingface_hub's retries."""
    import os
    import socket
    import subprocess
    import sys
    import time

    from tests.helpers import REPO

    with socket.socket() as s:  # a port nobody listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if not k.startswith("HF_")}
    env.update(HF_ENDPOINT=f"http://127.0.0.1:{port}", HF_HOME=str(tmp_path / "hf"), PYTHONPATH=str(REPO),
               RVGGT_WEIGHTS_DIR=str(tmp_path / "converted"), JAX_PLATFORMS="cpu")
    code = ("import sys, time\nfrom rvggt_jax.weights.hub import HubError, resolve_checkpoint\nt = time.monotonic()\n"
            "try: resolve_checkpoint('someone/some-model')\n"
            "except HubError as e: print(f'{time.monotonic() - t:.2f}', e); sys.exit(3)\n")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 3, r.stderr[-2000:]
    seconds, message = r.stdout.split(" ", 1)
    assert float(seconds) < 5, (seconds, time.monotonic() - t0)
    assert f"the hub (http://127.0.0.1:{port}) cannot be reached" in message and "someone/some-model" in message
