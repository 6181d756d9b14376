"""How the plans write sizes. A module without JAX: the command line formats with it before
any program is built (`rvggt --help` and argument errors do not start JAX)."""

from __future__ import annotations


def fmt_bytes(n: int | None) -> str:
    """Bytes in GiB (MiB, KiB for small programs)."""
    if n is None:
        return "n/a"
    for unit, size in (("GiB", 2 ** 30), ("MiB", 2 ** 20)):
        if abs(n) >= 0.1 * size:
            return f"{n / size:.2f} {unit}"
    return f"{n / 1024:.1f} KiB"
