"""`python -m rvggt_jax.convert SRC DST [--config config.json] [--no-track] [--quiet]` (see cli.py)."""

import sys

from rvggt_jax.convert.cli import main

if __name__ == "__main__":
    sys.exit(main())
