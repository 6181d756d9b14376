"""The verdict of `rvggt plan`: a memory report (`planning.memory.MemoryReport`) held
against the memory of its target, or another (`--memory-gb`), and the lines that say it.
Pure functions of the report: nothing here compiles."""

from __future__ import annotations

import dataclasses
import math

from rvggt_jax.planning.units import fmt_bytes

__all__ = ["JAX_GPU_FRACTION", "fits", "held_against", "judge", "memory_fraction_note", "planned_label", "share",
           "verdict"]

JAX_GPU_FRACTION = 0.75  # JAX's GPU client lets XLA use this share unless told otherwise


def share(n: int, have: int) -> str:
    """' (42%)': n as a share of `have` (nothing when `have` is unknown)."""
    return f" ({n / have:.0%})" if have else ""


def held_against(rep, gib: float | None):
    """`rep` held against `gib` GiB (--memory-gb) instead of its target's memory (None: as
    it is). A program XLA:TPU compiled was checked against the chip's HBM: `judge` reads
    its heap-simulation peak when G is less."""
    if gib is None:
        return rep
    what = f"--memory-gb {gib:g}, instead of {fmt_bytes(rep.memory_bytes)} ({rep.memory_what or rep.target})"
    return dataclasses.replace(rep, memory_bytes=int(gib * 2 ** 30), memory_what=what,
                               own_memory_bytes=rep.memory_bytes)


def judge(rep) -> tuple[bool, str, str]:
    """(fits, figure, what decides) of a report held against a known memory. One figure:
    XLA:TPU's refusal or heap-simulation peak (it compiles only what fits its HBM), else
    XLA's planned total against the memory; a plan that fits never shows a share over 100%.
    Held against less than the chip's HBM (--memory-gb, `held_against`), a program XLA:TPU
    compiled is judged by its heap-simulation peak (by its total, an upper bound, when
    XLA:TPU gave none); against more, a refused one by the size XLA:TPU said it needs."""
    have, mem = fmt_bytes(rep.memory_bytes), rep.memory_bytes
    if rep.exhausted:
        need = rep.needed_bytes
        if need <= mem:  # (--memory-gb above the chip's HBM)
            return (True, f"needs {fmt_bytes(need)} of {have}{share(need, mem)}",
                    "the size XLA:TPU said it needs when it refused the chip's HBM decides")
        return (False, f"needs {fmt_bytes(need)} of {have}{share(need, mem)}",
                "XLA:TPU refused to compile it: its own HBM check decides")
    if rep.compiler_checked:
        peak = rep.peak_bytes
        hbm = rep.own_memory_bytes or mem  # what XLA:TPU compiled it for
        if mem < hbm:  # (--memory-gb below the HBM XLA:TPU compiled it for: its check says nothing of G)
            figure, decides = ((peak, "XLA:TPU's heap-simulation peak decides") if peak else
                               (rep.total_bytes, "XLA:TPU's total decides, an upper bound: it may fit"))
            if figure <= mem:
                return (True, f"{fmt_bytes(figure)} of {have}{share(figure, mem)}, {fmt_bytes(mem - figure)} to "
                              f"spare", decides)
            return (False, f"needs {fmt_bytes(figure)} of {have}{share(figure, mem)}, short by "
                           f"{fmt_bytes(figure - mem)}", decides)
        shown = f", heap-simulation peak {fmt_bytes(peak)}{share(peak, mem)}" if peak and peak <= mem else ""
        if hbm < mem:  # (--memory-gb above it)
            return (True, f"compiled for the chip's {fmt_bytes(hbm)} of HBM, within the {have} held against{shown}",
                    "XLA:TPU's own HBM check decides, not the total")
        return True, f"compiled for the {have} of HBM{shown}", "XLA:TPU's own HBM check decides, not the total"
    total, spare = rep.total_bytes, rep.headroom_bytes
    figure = f"{fmt_bytes(total)} of {have}{share(total, mem)}"
    if spare >= 0:
        return True, f"{figure}, {fmt_bytes(spare)} to spare", "XLA's planned total decides"
    return False, f"needs {figure}, short by {fmt_bytes(-spare)}", "XLA's planned total decides"


def fits(rep) -> bool | None:
    """Whether the plan fits the memory it is held against (`judge`); None when unknown."""
    return None if rep.memory_bytes is None else judge(rep)[0]


def verdict(rep) -> str:
    """The plan's one verdict line: FITS or DOES NOT FIT, one figure, what decides."""
    fits, figure, decides = judge(rep)
    return f"{'FITS' if fits else 'DOES NOT FIT'}: {figure} ({decides})."


def planned_label(rep) -> str:
    fits, figure, _ = judge(rep)
    return f"planned, {'fits' if fits else 'does not fit'}: {figure}"


def memory_fraction_note(rep, target) -> str | None:
    """For a GPU plan that fits but needs more than JAX's default share of the card: the
    XLA_PYTHON_CLIENT_MEM_FRACTION to run with (None otherwise)."""
    if target.platform != "cuda" or not fits(rep) or rep.total_bytes <= JAX_GPU_FRACTION * rep.memory_bytes:
        return None
    need = math.ceil(100 * rep.total_bytes / rep.memory_bytes) / 100
    return (f"note: JAX lets XLA use {JAX_GPU_FRACTION:.0%} of a GPU's memory unless told otherwise: run with "
            f"XLA_PYTHON_CLIENT_MEM_FRACTION={min(need + 0.02, 0.99):.2f} (or more)")
