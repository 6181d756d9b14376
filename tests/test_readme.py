"""The README's Python code runs as written. Two strings are swapped, and only these:
the hub repo id becomes the bundled tiny checkpoint (tests never download) and the
user's image folder becomes the bundled images; both must be in the README, so a
changed snippet cannot skip this test."""

import re

import pytest

from tests.helpers import DEMO_IMAGES as IMAGES, REPO, TINY
SUBSTITUTE = {'"facebook/VGGT-1B"': repr(str(TINY)), '"my_images/*.jpg"': repr(str(IMAGES / "*.jpg"))}


def python_blocks() -> list[str]:
    text = (REPO / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_has_python_snippets():
    blocks = python_blocks()
    assert blocks, "the README has no ```python block"
    joined = "\n".join(blocks)
    for old in SUBSTITUTE:
        assert old in joined, f"{old} is no longer in the README's Python code: update tests/test_readme.py"


@pytest.mark.parametrize("i", range(len(python_blocks())))
def test_readme_python_block_runs(i, monkeypatch):
    monkeypatch.setenv("RVGGT_CACHE_DIR", "off")
    code = python_blocks()[i]
    for old, new in SUBSTITUTE.items():
        code = code.replace(old, new)
    scope: dict = {"__name__": "__readme__"}
    exec(compile(code, f"README.md python block {i}", "exec"), scope)
    if "query_points" in scope:  # the API snippet: tracks of every query point in every frame
        s = len(list(IMAGES.glob("*.jpg")))
        assert tuple(scope["out"]["track"].shape) == (1, s, len(scope["query_points"]), 2)
        assert tuple(scope["extrinsic"].shape) == (1, s, 3, 4)
