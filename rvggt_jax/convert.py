"""`python -m rvggt_jax.convert SRC DST [--config config.json] [--no-track] [--quiet]`, and
the converter's names under the path they had before the layout (`rvggt_jax.weights`)."""

import sys

from rvggt_jax.weights import *  # noqa: F401,F403 - the converter's public names
from rvggt_jax.weights import __all__ as _weights_all

__all__ = [*_weights_all, "main"]


def main(argv=None) -> int:
    """`python -m rvggt_jax.convert SRC DST ...`; returns the exit status."""
    from rvggt_jax.app.convert_command import main as _main

    return _main(argv)


if __name__ == "__main__":
    sys.exit(main())
