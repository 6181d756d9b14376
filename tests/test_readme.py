"""The README's Python code runs as written. Two strings are swapped, and only these:
the hub repo id becomes the bundled tiny checkpoint (tests never download) and the
user's image folder becomes the bundled images; both must be in the README, so a
changed snippet cannot skip this test. Its first two shell commands (install and demo;
test extras and suite) are what .ci/run runs."""

import re
import shlex

import pytest

from tests.helpers import SAMPLE_IMAGES as IMAGES, REPO, TINY
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


def _commands(line: str) -> list[list[str]]:
    """A shell line's commands (split at `&&`), each as its words without what only CI
    adds: `--quiet`, and the demo's output folder (`--out DIR` -> `--out OUT`)."""
    commands, words = [], []
    for w in shlex.split(line, comments=True) + ["&&"]:
        if w == "&&":
            commands.append([w for w in words if w != "--quiet"])
            words = []
        elif words[-1:] == ["--out"]:
            words.append("OUT")
        else:
            words.append(w)
    return commands


def readme_first_commands() -> list[list[str]]:
    """The commands of the first two lines of the README's first ```bash block."""
    block = re.search(r"```bash\n(.*?)```", (REPO / "README.md").read_text(), flags=re.S).group(1)
    return [c for line in block.splitlines()[:2] for c in _commands(line)]


# .ci/run's second step (the GPU check's dry run in an environment of its own) starts here
CI_SECOND_STEP = "# Second step:"


def ci_commands() -> list[list[str]]:
    """What .ci/run runs after making its virtual environment (less pip's own upgrade),
    up to its second step."""
    text = (REPO / ".ci" / "run").read_text().split(". .venv/bin/activate\n", 1)[1]
    lines = text.split(CI_SECOND_STEP, 1)[0].splitlines()
    return [c for line in lines for c in _commands(line) if c and c[-2:] != ["--upgrade", "pip"]]


def test_readme_first_commands_install_the_tool_then_the_tests():
    """Line 1 installs the package alone (no test or planning extras: the `plan` extra's
    CUDA and TPU plugins are for planning) and runs the demo; line 2 installs the test
    extras and runs the suite. The demo's folder is ignored by git."""
    install, demo, test_install, suite = readme_first_commands()
    assert install == ["pip", "install", "-e", "."]
    assert demo[:3] == ["rvggt", "demo", "--out"]
    assert test_install[:3] == ["pip", "install", "-e"] and {"test", "plan"} <= set(
        test_install[3].removeprefix(".[").removesuffix("]").split(","))
    assert suite[:3] == ["python", "-m", "pytest"]
    out = re.search(r"--out (\S+)", (REPO / "README.md").read_text().split("```bash\n", 1)[1]).group(1)
    assert f"/{out}/" in (REPO / ".gitignore").read_text().splitlines()


def test_ci_runs_the_readme_first_two_commands():
    assert ci_commands() == readme_first_commands()
