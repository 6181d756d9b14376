"""Checkpoints named by a Hugging Face repo id (`facebook/VGGT-1B`): downloaded with
`huggingface_hub` into its own cache (HF_HOME, HF_HUB_CACHE), converted once to an Orbax
checkpoint under the rvggt-jax cache and reused from there.

    resolve_checkpoint("facebook/VGGT-1B") -> Path of the converted Orbax folder
    resolve_checkpoint("weights/vggt-1b")  -> that local path, unchanged

Converted copies: `$RVGGT_WEIGHTS_DIR/<owner>--<name>/<commit>/` (default
`$XDG_CACHE_HOME/rvggt-jax/weights`, i.e. `~/.cache/rvggt-jax/weights`), one per hub
commit, so a new upstream revision is converted again and an old one is never mixed in.
Offline (`HF_HUB_OFFLINE=1`, or the endpoint not answering one quick TCP probe,
`hub_reachable`) the hub cache is used at once; when even that lacks the files, the
newest converted copy of the repo is used, and without one `HubError` says
exactly which file is missing where.

Concurrent runs: a copy is written into a temporary sibling folder, marked complete
(`.complete`, last), then renamed into place, so no reader ever sees a partial folder;
one run converts while the others wait on a lock file and then use its copy. A folder
left by a killed run (a temporary sibling, or a copy without its marker) is removed and
the conversion redone.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Callable

__all__ = ["HubError", "converted_root", "is_repo_id", "publish_dir", "resolve_checkpoint"]

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
_READY = ".complete"  # written last: a folder without it is an interrupted conversion
_PROBE_TIMEOUT_S = 3.0  # a reachable hub answers a TCP connect well within this
# owner/name as the hub spells them (letters, digits, '-', '_', '.'), nothing else
_REPO_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,95}/[A-Za-z0-9][A-Za-z0-9_.-]{0,95}$")


class HubError(RuntimeError):
    """A repo id that could not be resolved to a checkpoint (the message says why)."""


def is_repo_id(spec: str | os.PathLike) -> bool:
    """True for `owner/name` that is not an existing local path (a local path wins)."""
    s = os.fspath(spec)
    return bool(_REPO_ID.match(s)) and not Path(s).exists() and ".." not in s


def converted_root() -> Path:
    """Folder of the converted (Orbax) copies of hub checkpoints."""
    d = os.environ.get("RVGGT_WEIGHTS_DIR")
    if d:
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "rvggt-jax" / "weights"


def _repo_dir(repo_id: str) -> Path:
    return converted_root() / repo_id.replace("/", "--")


def _newest_converted(repo_id: str) -> Path | None:
    done = [p.parent for p in _repo_dir(repo_id).glob(f"*/{_READY}")]
    return max(done, key=lambda p: (p / _READY).stat().st_mtime) if done else None


def _hub_cache() -> str:
    from huggingface_hub import constants

    return str(constants.HF_HUB_CACHE)


def _endpoint() -> str:
    from huggingface_hub import constants

    return str(constants.ENDPOINT)


def _offline() -> bool:
    from huggingface_hub import constants

    return bool(constants.HF_HUB_OFFLINE)


def _download(repo_id: str, filename: str, revision: str | None, local_only: bool = False) -> str:
    from huggingface_hub import hf_hub_download

    return hf_hub_download(repo_id, filename, revision=revision, local_files_only=local_only)


def hub_reachable(timeout: float = _PROBE_TIMEOUT_S) -> bool:
    """Whether a TCP connection to the hub endpoint (HF_ENDPOINT, default huggingface.co;
    or to the proxy configured for it) opens within `timeout` seconds. One quick probe:
    unreachable, huggingface_hub would spend ~25 s in its retries before giving up."""
    import socket
    import urllib.parse
    import urllib.request

    from huggingface_hub import constants

    url = urllib.parse.urlsplit(constants.ENDPOINT)
    host, port = url.hostname, url.port or (443 if url.scheme == "https" else 80)
    proxy = urllib.request.getproxies().get(url.scheme)
    if proxy and host and not urllib.request.proxy_bypass(host):
        purl = urllib.parse.urlsplit(proxy if "://" in proxy else f"http://{proxy}")
        host, port = purl.hostname, purl.port or 80
    if not host:
        return True  # an endpoint we cannot parse: let huggingface_hub try it
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _explain(repo_id: str, filename: str, e: Exception) -> str:
    """Why `filename` of `repo_id` could not be had, and what to do, in one sentence."""
    name = type(e).__name__
    where = f"the Hugging Face cache ({_hub_cache()})"
    if name == "GatedRepoError":
        return (f"{repo_id} is gated: request access on its hub page, then log in (`hf auth login`) "
                f"or set HF_TOKEN")
    if name == "RepositoryNotFoundError":
        return f"no Hugging Face repo {repo_id} and no local path {repo_id} (misspelled? private repos need `hf auth login`)"
    if name in ("EntryNotFoundError", "RemoteEntryNotFoundError"):
        return f"{repo_id} has no {filename} (rvggt-jax reads the safetensors checkpoint)"
    if name == "RevisionNotFoundError":
        return f"{repo_id} has no such revision"
    if _offline() or name in ("LocalEntryNotFoundError", "OfflineModeIsEnabled"):
        how = "HF_HUB_OFFLINE is set" if _offline() else f"the hub ({_endpoint()}) cannot be reached"
        return (f"{filename} of {repo_id} is not in {where} and {how}; no converted copy in "
                f"{_repo_dir(repo_id)} either (and no local path {repo_id}): download it once online "
                f"(`hf download {repo_id} {filename} {CONFIG_FILE}`) or pass a local checkpoint")
    return f"cannot download {filename} of {repo_id}: {name}: {e}"


def resolve_checkpoint(spec: str | os.PathLike, *, revision: str | None = None, progress: bool = False,
                       say: Callable[[str], None] | None = None) -> Path:
    """A local checkpoint path for `spec`: itself when it is a local path (or does not
    look like `owner/name`), else the converted Orbax copy of the hub repo (downloaded
    and converted on first use). Raises `HubError` with the reason."""
    if not is_repo_id(spec):
        return Path(spec)
    repo_id = os.fspath(spec)
    say = say or (lambda msg: None)
    local_only = not _offline() and not hub_reachable()  # then only the caches, at once
    try:
        st = Path(_download(repo_id, WEIGHTS_FILE, revision, local_only))
    except Exception as e:  # noqa: BLE001 - every hub failure becomes one explanation
        fallback = _newest_converted(repo_id)
        if fallback is not None and type(e).__name__ not in ("GatedRepoError", "RepositoryNotFoundError"):
            say(f"{repo_id}: hub not reachable ({type(e).__name__}); using the converted copy {fallback}")
            return fallback
        raise HubError(_explain(repo_id, WEIGHTS_FILE, e)) from None
    commit = st.parent.name  # .../snapshots/<commit>/model.safetensors
    dst = _repo_dir(repo_id) / commit
    if (dst / _READY).is_file():
        return dst
    try:
        cfg = Path(_download(repo_id, CONFIG_FILE, commit, local_only))
    except Exception:  # noqa: BLE001 - no config.json: the layout is inferred from the shapes
        cfg = None
    with _cache_lock(dst, say) as locked:
        # another run may have converted it while this one waited
        if (dst / _READY).is_file():
            return dst
        if locked:  # no other run is writing now: what temporaries there are, killed runs left
            clear_stale_temporaries(dst)
        say(f"converting {repo_id} ({commit[:12]}) once to {dst} ...")
        _convert_to(st, cfg, dst, progress)
    return dst


@contextlib.contextmanager
def _cache_lock(dst: Path, say: Callable[[str], None]):
    """Hold `dst`'s lock file (an OS advisory lock, released when the process dies): one
    run converts, the others wait for it and find the copy done. Where there are no such
    locks (Windows), the atomic rename alone keeps readers safe."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield False
        return
    with open(dst.parent / f".{dst.name}.lock", "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            say(f"waiting for another run converting into {dst} ...")
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield True
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def publish_dir(tmp: Path, dst: Path, marker: str = _READY) -> Path:
    """Move the finished folder `tmp` (holding `marker`, written last) to `dst` by one
    rename, so a reader sees no `dst` or a complete one. When a complete `dst` appeared
    meanwhile (another run won), `tmp` is discarded and theirs is used. A `dst` without
    its marker is a partial copy of an interrupted run: moved aside and replaced. `tmp`
    must be a sibling of `dst` (same file system). Returns `dst`."""
    for _ in range(8):
        if (dst / marker).is_file():
            shutil.rmtree(tmp, ignore_errors=True)
            return dst
        if dst.exists():
            aside = Path(tempfile.mkdtemp(prefix=f".{dst.name}.partial-", dir=dst.parent))
            try:
                os.replace(dst, aside / dst.name)
            except FileNotFoundError:  # another run moved it first
                pass
            shutil.rmtree(aside, ignore_errors=True)
        try:
            os.rename(tmp, dst)  # fails when dst exists again (non-empty): look once more
            return dst
        except OSError:
            continue
    raise HubError(f"could not move the converted copy {tmp} to {dst}: the folder keeps changing")


def clear_stale_temporaries(dst: Path) -> None:
    """Remove the temporary siblings of `dst` that interrupted runs left behind (called
    under `dst`'s lock, when no other run is writing one)."""
    for p in dst.parent.glob(f".{dst.name}.*"):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)


def _convert_to(st: Path, cfg: Path | None, dst: Path, progress: bool) -> None:
    """Convert the safetensors `st` (config `cfg` or inferred) into `dst`, atomically:
    into a temporary sibling first, marked complete, then renamed into place
    (`publish_dir`)."""
    import jax

    from rvggt_jax.weights.converter import load_safetensors
    from rvggt_jax.weights.checkpoint import config_for_safetensors, save_orbax

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a config.json the hub mixin wrote is fine; inference is reported by load
        config = config_for_safetensors(st, cfg)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=dst.parent))
    try:
        cpu = jax.devices("cpu")[0]
        params = load_safetensors(st, config, progress=progress, leaf_fn=lambda x: jax.device_put(x, cpu))
        save_orbax(params, config, tmp, overwrite=True)
        (tmp / _READY).write_text(str(st) + "\n")
        publish_dir(tmp, dst)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
