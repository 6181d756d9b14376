"""`rvggt --version`, `--help` and argument errors answer before JAX is imported: about 0.3 s
where importing JAX took 2.5 s more (the parser's COLMAP camera models and the plan's size
format had imported it, through `rvggt_jax.geometry` and `planning.memory`)."""

import os
import subprocess
import sys

from tests.helpers import REPO

CODE = r"""
import contextlib, io, sys
from rvggt_jax.app import cli
for argv in (["--version"], ["--help"], ["reconstruct", "--help"], ["plan", "--help"], ["frobnicate"],
             ["reconstruct", "imgs", "--camera-type", "fisheye"]):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
        try:
            cli.main(argv)
        except SystemExit:
            pass
    if argv[-1] == "fisheye":
        assert "FISHEYE" in err.getvalue(), err.getvalue()  # (the choices, named)
print(sorted(m for m in ("jax", "jaxlib", "ml_dtypes") if m in sys.modules))
"""


def test_help_version_and_argument_errors_do_not_import_jax():
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout
