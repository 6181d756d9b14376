"""How fast each accelerator `rvggt plan` knows multiplies and talks to its neighbours: the
vendors' peak dense FLOP/s per dtype (`Peaks`) and interconnect bandwidth (`Link`), each
figure with its source. `planning.targets` gives every target its figures;
`planning.target_time` turns them into the plan's time estimate and ring line.
"""

from __future__ import annotations

import dataclasses

__all__ = ["A100", "A6000", "HOPPER", "ICI_V5E", "ICI_V5P", "ICI_V6E", "Link", "NVLINK3", "NVLINK4", "PCIE4", "PCIE5",
           "Peaks", "RTX4090", "RTX5090", "TPU_V5E", "TPU_V5P", "TPU_V6E"]


@dataclasses.dataclass(frozen=True)
class Peaks:
    """Peak dense FLOP/s of one GPU or chip (no 2:4 sparsity), as the vendor publishes
    them, for the ways this project runs a product (`VGGTConfig.dot_precision`,
    `rvggt_jax/ops/precision.py`):

    bf16     bfloat16 operands, float32 accumulation: a bfloat16 config's aggregator;
    f32      float32 at "highest", what a float32 config runs: no TF32 on a GPU (its
             CUDA cores' FP32 rate), six bfloat16 passes on a TPU;
    f32_default  float32 at the platform's default, what a bfloat16 config's float32
             heads run: TF32 tensor cores on a GPU, one bfloat16 pass on a TPU;
    source   where the figures come from; f32_how, f32_default_how: how the platform
             runs the two float32 ways (as the plan prints them).
    """

    bf16: float
    f32: float
    f32_default: float
    source: str
    f32_how: str = "FP32, no TF32"  # how the platform runs float32 at "highest"
    f32_default_how: str = "TF32"  # and at its default
    f32_high: float | None = None  # float32 at "high" (None: as at the default; a TPU: three bf16 passes)

    def __post_init__(self):
        if min(self.bf16, self.f32, self.f32_default) <= 0:
            raise ValueError(f"peak FLOP/s must be positive; got {self}")

    def of(self, dtype: str, precision: str | None = "highest") -> tuple[float, str]:
        """(FLOP/s, what) of products with `dtype` operands ("bfloat16", "float32") at
        `precision` (float32 only: "highest"; "high"; "default" or None, the platform's
        fast path: TF32 or one bf16 pass)."""
        if dtype == "bfloat16":
            return self.bf16, "bf16"
        if dtype != "float32":
            raise ValueError(f"peak FLOP/s of {dtype!r} products: only bfloat16 and float32 are known")
        if precision == "highest":
            return self.f32, f"float32 at highest ({self.f32_how})"
        if precision == "high" and self.f32_high is not None:
            return self.f32_high, "float32 at high (three bf16 passes)"
        return self.f32_default, f"float32 at {precision or 'default'} ({self.f32_default_how})"


@dataclasses.dataclass(frozen=True)
class Link:
    """What one device of a target sends to its ring neighbour while it receives as
    much: bytes_per_s one way (half the vendor's bidirectional figure), over `links`
    links (a ring step to one neighbour may take only one of them: `links` times
    longer), `name` (NVLink 4, ICI, PCIe 4.0 x16) and `source`."""

    name: str
    bytes_per_s: float
    source: str
    links: int = 1

    def __post_init__(self):
        if self.bytes_per_s <= 0 or self.links < 1:
            raise ValueError(f"a link needs a positive bandwidth and at least one link; got {self}")


_T = 1e12  # TFLOP/s
_GB = 1e9  # the vendors' GB/s are decimal

# Peak dense FLOP/s (the vendors' tables give 2:4-sparse figures as well: twice these).
# NVIDIA H100 SXM and H200 SXM datasheets: BF16 tensor 1,979 TFLOP/s with sparsity (989.4
# dense), TF32 989 with sparsity (494.7 dense), FP32 67 (66.9 in the Hopper whitepaper's
# table); the H200 is the same GH100 compute with more memory.
HOPPER = Peaks(989.4 * _T, 66.9 * _T, 494.7 * _T, "NVIDIA H100 / H200 SXM datasheets (dense)")
# NVIDIA A100 datasheet: BF16 tensor 312, TF32 156, FP32 19.5 TFLOP/s (SXM, 40 and 80 GB)
A100 = Peaks(312 * _T, 19.5 * _T, 156 * _T, "NVIDIA A100 datasheet (dense)")
# NVIDIA RTX A6000 datasheet: BF16 tensor 154.8 (309.7 sparse), TF32 77.4 (154.8 sparse),
# FP32 38.7 TFLOP/s
A6000 = Peaks(154.8 * _T, 38.7 * _T, 77.4 * _T, "NVIDIA RTX A6000 datasheet (dense)")
# NVIDIA Ada whitepaper, RTX 4090: BF16 tensor with FP32 accumulate (what XLA's bf16
# products ask for; GeForce cards run it at half the FP16-accumulate rate) 165.2, TF32
# 82.6, FP32 82.6 TFLOP/s
RTX4090 = Peaks(165.2 * _T, 82.6 * _T, 82.6 * _T, "NVIDIA Ada GPU architecture whitepaper, RTX 4090 (dense, "
                                                 "FP32 accumulate)")
# NVIDIA RTX Blackwell whitepaper, RTX 5090: FP16/BF16 tensor 838 TFLOP/s sparse with FP16
# accumulate, so 209.5 dense with FP32 accumulate (half rate on GeForce, as the 4090),
# TF32 104.8, FP32 104.8
RTX5090 = Peaks(209.5 * _T, 104.8 * _T, 104.8 * _T, "NVIDIA RTX Blackwell GPU architecture whitepaper, RTX 5090 "
                                                   "(dense, FP32 accumulate)")


def _tpu_peaks(bf16: float, source: str) -> Peaks:
    # A TPU multiplies bfloat16 only: a float32 product at "highest" is six bf16 passes
    # (XLA's algorithm ALG_DOT_BF16_BF16_F32_X6), at "high" three (_X3), at "default" one
    return Peaks(bf16, bf16 / 6, bf16, source + "; float32 at highest: six bf16 passes (a sixth)",
                 f32_how="six bf16 passes", f32_default_how="one bf16 pass", f32_high=bf16 / 3)


# Google Cloud TPU docs (docs.cloud.google.com/tpu/docs/v5e, v6e, v5p-training), per chip:
# peak bf16 197 / 918 / 459 TFLOP/s; bidirectional ICI bandwidth 400 / 800 / 1200 GB/s
# over 4 / 4 / 6 ICI ports
TPU_V5E = _tpu_peaks(197 * _T, "Google Cloud TPU v5e docs: 197 TFLOP/s bf16 per chip")
TPU_V6E = _tpu_peaks(918 * _T, "Google Cloud TPU v6e docs: 918 TFLOP/s bf16 per chip")
TPU_V5P = _tpu_peaks(459 * _T, "Google Cloud TPU v5p docs: 459 TFLOP/s bf16 per chip (two cores, megacore)")
ICI_V5E = Link("ICI", 200 * _GB, "Google Cloud TPU v5e docs: 400 GB/s bidirectional ICI per chip, 4 ports", 4)
ICI_V6E = Link("ICI", 400 * _GB, "Google Cloud TPU v6e docs: 800 GB/s bidirectional ICI per chip, 4 ports", 4)
ICI_V5P = Link("ICI", 600 * _GB, "Google Cloud TPU v5p docs: 1200 GB/s bidirectional ICI per chip, 6 ports", 6)
# NVIDIA datasheets: NVLink 900 GB/s (H100, H200 SXM) and 600 GB/s (A100 SXM) per GPU,
# bidirectional, through NVSwitch to any GPU of the host; PCIe (no NVLink: the GeForce
# cards; the A6000's NVLink bridge joins two cards only): 4.0 x16 ~64 GB/s, 5.0 x16 ~128
# GB/s bidirectional
NVLINK4 = Link("NVLink 4", 450 * _GB, "NVIDIA H100 / H200 SXM datasheets: NVLink 900 GB/s bidirectional")
NVLINK3 = Link("NVLink 3", 300 * _GB, "NVIDIA A100 SXM datasheet: NVLink 600 GB/s bidirectional")
PCIE4 = Link("PCIe 4.0 x16", 32 * _GB, "PCIe 4.0 x16: 64 GB/s bidirectional")
PCIE5 = Link("PCIe 5.0 x16", 64 * _GB, "PCIe 5.0 x16: 128 GB/s bidirectional")
