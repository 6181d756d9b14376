"""What the test modules share: plain functions and constants (pytest fixtures live in
tests/conftest.py). Test modules import from here, never from one another.

This file imports nothing heavy: `grad_fd.py` and `sharded_worker.py` run as scripts
that must configure JAX (x64, the host device count) before JAX or rvggt_jax is imported.
The other helpers are modules of their own (`from tests.helpers.micro import micro_config`).
"""

from tests.helpers.paths import DATA, SAMPLE_IMAGES, HELPERS, PACKAGE, PREPROCESS, REPO, TINY
from tests.helpers.metrics import rel_err

__all__ = ["DATA", "SAMPLE_IMAGES", "HELPERS", "PACKAGE", "PREPROCESS", "REPO", "TINY", "rel_err"]
