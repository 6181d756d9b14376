"""rvggt-jax: VGGT in JAX/Flax with the training-free RegimeVGGT accelerator.

    params, config = rvggt_jax.load_pretrained("weights/")
    out = jax.jit(rvggt_jax.rvggt_forward)(params, images, config.with_compression("regime"))
"""

import importlib

# Public names resolved on first use, so importing a submodule (rvggt_jax.model.layers) stays
# cheap and does not pull in every head, and `import rvggt_jax` alone imports no JAX (the
# `rvggt` command sets up the process before JAX is imported: rvggt_jax.app.cli.main).
_LAZY = {
    "VGGTConfig": "rvggt_jax.config",
    "rvggt_forward": "rvggt_jax.model.forward",
    "as_query_points": "rvggt_jax.model.inputs",
    "InputError": "rvggt_jax.errors",
    "InputRangeWarning": "rvggt_jax.model.input_range",
    "warn_if_out_of_range": "rvggt_jax.model.input_range",
    "load_pretrained": "rvggt_jax.weights.pretrained",
    "load_images": "rvggt_jax.io.images",
    "cost_report": "rvggt_jax.planning.cost",
    "memory_report": "rvggt_jax.planning.memory",
    "init_params": "rvggt_jax.model.modules",
    "sharded_forward": "rvggt_jax.parallel.sharded",
    "frames_mesh": "rvggt_jax.parallel.sharded",
    # multi-threaded XLA:CPU convolutions; importing rvggt_jax leaves os.environ alone, the
    # `rvggt` command calls it (see rvggt_jax.app.xla_cpu)
    "prefer_threaded_convolutions": "rvggt_jax.app.xla_cpu",
    # glibc's malloc keeping freed memory for the next run (rvggt_jax.app.host_heap); the
    # `rvggt` command calls it
    "keep_freed_host_memory": "rvggt_jax.app.host_heap",
}
__all__ = [*_LAZY]
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'rvggt_jax' has no attribute {name!r}")
