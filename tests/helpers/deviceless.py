"""Abstract inputs placed on a GPU or TPU that is not there: XLA's own compilers run on
this CPU host (deviceless ahead-of-time compilation; the `[plan]` extra)."""

from __future__ import annotations

import functools
from pathlib import Path

import jax
from jax.experimental import topologies

_H200 = Path(__file__).resolve().parents[3] / "shared" / "accel" / "h200.txtpb"


@functools.cache
def device(name: str):
    """The abstract device of target `name` ("h200" or "tpu-v6e")."""
    if name == "h200":
        return topologies.get_topology_desc(platform="cuda", target_config=_H200.read_text(),
                                            topology="1x1x1").devices[0]
    return topologies.get_topology_desc(platform="tpu", topology_name="v6e:1x1", chip_config_name="default",
                                        chips_per_host_bounds=(1, 1, 1), num_slices=1,
                                        wrap=(False, False, False)).devices[0]


def on(dev, shape, dtype) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(shape, dtype, sharding=jax.sharding.SingleDeviceSharding(dev))
