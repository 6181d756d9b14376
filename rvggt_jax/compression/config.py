"""Compression configuration of the global blocks.

Placeholder for the dense preset; the RegimeVGGT presets extend this module.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping


@dataclass(frozen=True)
class CompressionConfig:
    """`name == "dense"`: every global block is the upstream block."""

    name: str = "dense"

    @property
    def is_dense(self) -> bool:
        return self.name == "dense"

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CompressionConfig":
        return cls(**dict(d))


PRESETS = ("dense",)


def make_compression(name: str, depth: int, **overrides: Any) -> CompressionConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown compression preset {name!r}; known: {', '.join(PRESETS)}")
    return dataclasses.replace(CompressionConfig(name=name), **overrides)
