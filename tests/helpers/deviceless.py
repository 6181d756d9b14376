"""Abstract inputs placed on a GPU or TPU that is not there: XLA's own compilers run on
this CPU host (deviceless ahead-of-time compilation; the `[plan]` extra). The devices are
`rvggt_jax.planning.targets`' (its XLA target descriptions ship with the package)."""

from __future__ import annotations

import jax

from rvggt_jax.planning.targets import target_device


def device(name: str):
    """The abstract device of target `name` ("h200", "tpu-v6e", or any name or alias of
    `rvggt_jax.planning.targets.TARGETS`; cached)."""
    return target_device(name)


def on(dev, shape, dtype) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(shape, dtype, sharding=jax.sharding.SingleDeviceSharding(dev))
