"""`python -m convert SRC DST [--config config.json] [--no-track] [--quiet]` (see convert/cli.py)."""

import sys

from convert.cli import main

if __name__ == "__main__":
    sys.exit(main())
