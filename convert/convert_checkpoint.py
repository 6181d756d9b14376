"""Convert the published PyTorch VGGT checkpoint (`model.safetensors`, no torch needed) into
rvggt-jax's parameter tree, saved as an Orbax checkpoint:

    python convert/convert_checkpoint.py model.safetensors weights/ [--config config.json] [--no-track]

A thin entry over the package's converter (`rvggt_jax.weights`); the same command is
`rvggt convert`.
"""

import sys

from rvggt_jax.app.convert_command import main

if __name__ == "__main__":
    sys.exit(main(prog="python convert/convert_checkpoint.py"))
