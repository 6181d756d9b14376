"""A Hugging Face hub cache laid out as huggingface_hub lays it out, holding the tiny test
checkpoint (the tests never use the network)."""

import shutil
from pathlib import Path

from tests.helpers.paths import TINY

COMMIT = "0123456789abcdef0123456789abcdef01234567"


def populate_hub_cache(hf_home: Path, repo_id: str, files=("model.safetensors", "config.json")) -> Path:
    """HF_HOME/hub/models--owner--name/{refs/main, snapshots/<commit>/...}, as a download leaves it."""
    repo = hf_home / "hub" / ("models--" + repo_id.replace("/", "--"))
    snap = repo / "snapshots" / COMMIT
    snap.mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(COMMIT)
    for f in files:
        shutil.copy(TINY / f, snap / f)
    return repo
