"""Can XLA plan host offload for a target without its device? (issue 24's moonshot)

    python benchmarks/offload_probe.py --target h200 tpu-v6e cpu

For each target: the memory spaces its (deviceless) device lists, and XLA's plan of a
program that keeps six [8192, 8192] float32 arrays (256 MiB each) until its end, once
in device memory and once moved to `pinned_host` between their use and their reads.
Where the placement reaches XLA, the second plan's device temporaries drop and its host
temporaries grow. Needs the `[plan]` extra for the accelerator targets.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jax.sharding import SingleDeviceSharding  # noqa: E402

from rvggt_jax.planning import targets  # noqa: E402

N, KEPT = 8192, 6


def program(on_device, on_host):
    def f(x):
        kept = []
        for i in range(KEPT):
            x = jnp.tanh(x @ x) + i
            kept.append(x * 2 if on_host is None else jax.device_put(x * 2, on_host))
        out = x
        for k in kept:
            out = out + jnp.sin(k if on_host is None else jax.device_put(k, on_device))
        return out
    return f


def probe(name: str) -> None:
    dev = jax.devices("cpu")[0] if name == "cpu" else targets.target_device(name)
    try:
        kinds = [m.kind for m in dev.addressable_memories()]
    except Exception as e:  # noqa: BLE001 - a device that cannot say is an answer too
        kinds = f"error: {e}"
    on_device = SingleDeviceSharding(dev)
    x = jax.ShapeDtypeStruct((N, N), jnp.float32, sharding=on_device)
    print(f"{name}: {dev}; memory spaces {kinds}")
    for label, host in (("kept on the device", None), ("kept in pinned_host", SingleDeviceSharding(
            dev, memory_kind="pinned_host"))):
        try:
            m = jax.jit(program(on_device, host)).lower(x).compile().memory_analysis()
            print(f"  {label:20s} device temporaries {m.temp_size_in_bytes / 2**30:.2f} GiB, "
                  f"host temporaries {m.host_temp_size_in_bytes / 2**30:.2f} GiB")
        except Exception as e:  # noqa: BLE001 - report the compiler's refusal and go on
            print(f"  {label:20s} failed: {str(e).splitlines()[0][:200]}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--target", nargs="+", default=["h200", "cpu"])
    for name in ap.parse_args(argv).target:
        probe(name)


if __name__ == "__main__":
    main()
