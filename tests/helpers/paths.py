"""Every path the tests use, defined once: the repository, the package, the fixtures."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "rvggt_jax"
HELPERS = REPO / "tests" / "helpers"
DATA = REPO / "tests" / "data"
TINY = DATA / "vggt_tiny"  # the tiny upstream checkpoint and its golden outputs (tests/data/README.md)
PREPROCESS = DATA / "preprocess"  # upstream's image preprocessing of a few images
SAMPLE_IMAGES = PACKAGE / "examples_data" / "images"
