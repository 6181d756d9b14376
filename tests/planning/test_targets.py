"""Named accelerators planned without the device (rvggt_jax.planning.targets): every target
resolves by its names and compiles a small program here with XLA's own compiler for it
(the `[plan]` extra); a GPU plan holds cuDNN's attention and is held against the card's
memory, also for a card planned with another card's description; XLA:TPU's refusal of a
program larger than HBM becomes a report that does not fit; unknown names and missing
compilers say what to do."""

from __future__ import annotations

import dataclasses
import sys
import types

import jax
import jax.numpy as jnp
import pytest

from rvggt_jax.ops.attention import attention
from rvggt_jax.planning import targets as tg
from rvggt_jax.planning.memory import memory_report
from tests.helpers.deviceless import on
from tests.helpers.micro import plan_config

GiB = 2 ** 30
# XLA:TPU's refusal as libtpu 0.0.42.1 (jax 0.10.2) printed it for a program of 49 GiB on a
# v5e (`_oversized` below compiles it again)
CAPTURED = ("RESOURCE_EXHAUSTED: Ran out of memory on HBM, the total memory required for HLO temporaries "
            "(49.00G) exceeds available HBM (15.75G).")
KERNEL = {"cuda": "__cudnn$fmha", "tpu": "tpu_custom_call"}
# the card XLA compiles for: its description's name (the nearest one for the GeForce cards)
KIND = {"h100": "NVIDIA H100 80GB HBM3", "h200": "NVIDIA H200 141GB HBM3e", "a100-40gb": "NVIDIA A100-SXM4-40GB",
        "a100-80gb": "NVIDIA A100-SXM4-80GB", "a6000": "NVIDIA RTX A6000", "rtx4090": "NVIDIA RTX A6000",
        "rtx5090": "NVIDIA RTX PRO 6000 Blackwell", "tpu-v5e": "TPU v5 lite", "tpu-v6e": "TPU v6 lite",
        "tpu-v5p": "TPU v5", "cpu": "cpu"}


def _layer(x, w):
    """One attention layer: x [1, 128, 2, 64] bfloat16, w [64, 64]; the library's op picks
    the kernel of the platform compiled for."""
    return attention(x, x, x) @ w


@pytest.mark.parametrize("name", list(tg.TARGETS))
def test_every_target_compiles_a_small_program_with_its_kernel(name):
    target = tg.TARGETS[name]
    dev = tg.target_device(name)
    assert dev.device_kind == KIND[name]
    lowered = jax.jit(_layer).lower(on(dev, (1, 128, 2, 64), jnp.bfloat16), on(dev, (64, 64), jnp.bfloat16))
    text = lowered.as_text()
    for platform, mark in KERNEL.items():
        assert (mark in text) == (platform == target.platform), (name, platform)
    m = lowered.compile(compiler_options=target.options() or None).memory_analysis()
    assert m.output_size_in_bytes == 128 * 2 * 64 * 2
    assert m.argument_size_in_bytes >= (128 * 2 + 64) * 64 * 2


def test_names_and_aliases_resolve_in_any_spelling():
    for t in tg.TARGETS.values():
        for name in (t.name, t.name.upper(), *t.aliases):
            assert tg.get_target(name) is t, name
    assert tg.get_target("H200").name == "h200"
    assert tg.get_target("TPU v6e").name == tg.get_target("tpu_v6e").name == tg.get_target("v6e").name == "tpu-v6e"
    assert tg.get_target("NVIDIA GeForce RTX 4090").name == "rtx4090"
    assert tg.get_target(tg.TARGETS["cpu"]) is tg.TARGETS["cpu"]


def test_an_unknown_target_lists_the_choices():
    with pytest.raises(tg.UnknownTargetError, match="unknown target 'h300'; choose one of: h100, h200,.*tpu-v6e"):
        tg.get_target("h300")
    with pytest.raises(tg.UnknownTargetError, match="tpu-v5e"):
        memory_report(plan_config(), 2, 28, 28, target="gtx1080")


def test_a_target_is_checked_when_made():
    with pytest.raises(ValueError, match="names its XLA description"):
        tg.Target("x", "x", "cuda", GiB)
    with pytest.raises(ValueError, match="platform must be one of"):
        tg.Target("x", "x", "rocm", GiB)
    with pytest.raises(ValueError, match="memory_bytes must be positive"):
        tg.Target("x", "x", "tpu", 0, tpu_type="v6e")


def test_gpu_plan_holds_cudnn_and_a_nearest_description_is_held_against_the_cards_memory():
    # the RTX 4090: no description in XLA, planned as the RTX A6000 (48 GiB), held against 24 GiB;
    # the depth head's gemms need the Ampere workaround (NO_TRITON_GEMM)
    rep = memory_report(plan_config("depth"), 3, 28, 42, dtype="bfloat16", target="RTX 4090")
    assert rep.target == "rtx4090" and rep.device_kind == "NVIDIA RTX A6000" and rep.attention == "cudnn"
    assert "a6000.txtpb" in tg.TARGETS["rtx4090"].described_by and "24 GiB" in tg.TARGETS["rtx4090"].note
    assert rep.memory_bytes == 24 * GiB < tg.TARGETS["a6000"].memory_bytes
    assert rep.fits and rep.headroom_bytes == 24 * GiB - rep.total_bytes
    assert rep.total_bytes == rep.argument_bytes + rep.output_bytes + rep.temp_bytes - rep.alias_bytes > 0
    small = dataclasses.replace(rep, memory_bytes=rep.total_bytes - 1)  # the same plan on a smaller card
    assert small.fits is False and small.headroom_bytes == -1
    assert "for rtx4090 of 24.0 GiB: fits" in str(rep)
    assert not rep.compiler_checked  # XLA:GPU plans a program of any size: the sum is the verdict


def test_tpu_plan_fits_and_names_the_pallas_kernel():
    rep = memory_report(plan_config(), 3, 28, 42, target="tpu-v6e")
    assert rep.fits and rep.attention == "tpu_flash" and not rep.exhausted
    assert rep.memory_bytes == tg.TARGETS["tpu-v6e"].memory_bytes and 0 < rep.total_bytes < rep.memory_bytes
    # XLA:TPU compiles only what fits its HBM: the compile is the verdict, whatever the sum of
    # its memory analysis says (an upper bound on the chip)
    assert rep.compiler_checked and dataclasses.replace(rep, temp_bytes=rep.memory_bytes).fits
    assert "an upper bound" in str(rep)
    assert 0 < rep.peak_bytes <= rep.total_bytes  # XLA's heap-simulator peak, from jaxlib's stats


def _oversized(a):
    """a [2^28] float32 (1 GiB) -> 20 sorted copies held at once: 49 GiB for XLA:TPU."""
    copies = jnp.stack([jnp.sort(a + i) for i in range(20)])
    return jnp.cumsum(copies[::-1], axis=0)[:, :10]


def test_the_refusal_parser_reads_xla_tpus_own_message():
    assert tg.exhausted_hbm(CAPTURED) == (49 * GiB, round(15.75 * GiB))
    dev = tg.target_device("tpu-v5e")
    with pytest.raises(Exception, match="RESOURCE_EXHAUSTED") as caught:  # the message of this libtpu, now
        jax.jit(_oversized).lower(on(dev, (2 ** 28,), jnp.float32)).compile()
    needed, available = tg.exhausted_hbm(str(caught.value))
    assert needed > 40 * GiB and abs(available - tg.TARGETS["tpu-v5e"].memory_bytes) < 0.01 * GiB
    assert tg.exhausted_hbm("RESOURCE_EXHAUSTED: Used 20.5G of 15.75G hbm. Exceeded hbm capacity by 4.75G.") == (
        round(20.5 * GiB), round(15.75 * GiB))  # older libtpu's wording
    assert tg.exhausted_hbm("INTERNAL: something else (20.00G) exceeds available HBM (15.75G)") is None
    assert tg.exhausted_hbm("RESOURCE_EXHAUSTED: out of host memory") is None


def test_a_program_larger_than_hbm_is_a_report_that_does_not_fit():
    # 6000 frames of 518 x 518: 18 GiB of images alone on a 16 GiB v5e
    rep = memory_report(plan_config(), 6000, 518, 518, target="tpu-v5e")
    assert rep.exhausted and rep.fits is False and rep.compiled is None
    assert rep.total_bytes == rep.needed_bytes > 6000 * 3 * 518 * 518 * 4 > rep.memory_bytes
    assert rep.argument_bytes is None and rep.headroom_bytes < 0 and rep.attention == "tpu_flash"
    assert "XLA refused it" in str(rep) and "does not fit" in str(rep)


def test_slices_of_several_devices():
    assert tg._tpu_shape(tg.TARGETS["tpu-v6e"], 1) == ("v6e:1x1", (1, 1, 1))
    assert tg._tpu_shape(tg.TARGETS["tpu-v6e"], 8) == ("v6e:2x4", (2, 4, 1))
    assert tg._tpu_shape(tg.TARGETS["tpu-v6e"], 32) == ("v6e:4x8", (2, 4, 1))
    assert tg._tpu_shape(tg.TARGETS["tpu-v5p"], 8) == ("v5p:2x2x2", (2, 2, 1))
    assert len(tg.target_devices("tpu-v6e", 4)) == 4 and len(tg.target_devices("h100", 8)) == 8
    with pytest.raises(ValueError, match="power of two"):
        tg.target_devices("tpu-v6e", 3)
    with pytest.raises(ValueError, match="whole hosts of 8"):
        tg.target_devices("h200", 12)


def test_a_target_of_ones_own_reads_its_description_from_a_path(tmp_path):
    spec = tmp_path / "my_h200.txtpb"
    spec.write_text(tg.description_text(tg.TARGETS["h200"]).replace("NVIDIA H200 141GB HBM3e", "my H200"))
    mine = tg.Target("my-h200", "my H200 at 100 GiB", "cuda", 100 * GiB, description=str(spec))
    assert tg.target_device(mine).device_kind == "my H200"
    with pytest.raises(FileNotFoundError, match="no description 'gone.txtpb'"):
        tg.target_device(dataclasses.replace(mine, description="gone.txtpb"))


@pytest.mark.parametrize("name, modules", [("h100", ("jax_cuda12_plugin", "jax_cuda13_plugin")),
                                           ("tpu-v5p", ("libtpu",))])
def test_a_missing_compiler_says_what_to_install(monkeypatch, name, modules):
    for module in modules:
        monkeypatch.setitem(sys.modules, module, None)  # the import fails, as when not installed
    with pytest.raises(tg.CompilerMissingError, match=r'pip install "rvggt-jax\[plan\]"') as e:
        tg.target_device(name)
    assert all(module in str(e.value) for module in modules)
    with pytest.raises(tg.CompilerMissingError, match="rvggt-jax"):
        memory_report(plan_config(), 2, 28, 28, target=name)


@pytest.mark.parametrize("missing, present", [("jax_cuda12_plugin", "jax_cuda13_plugin"),
                                              ("jax_cuda13_plugin", "jax_cuda12_plugin")])
def test_either_cuda_plugin_carries_the_gpu_compiler(monkeypatch, missing, present):
    # images with CUDA 13 (the lent H200's) ship jax_cuda13_plugin, the [plan] extra 12
    monkeypatch.setitem(sys.modules, missing, None)
    monkeypatch.setitem(sys.modules, present, types.ModuleType(present))
    monkeypatch.setattr("rvggt_jax.ops.attention.compilable_platforms", lambda: ("cuda",))
    tg.check_compiler(tg.TARGETS["h100"])  # no error
    monkeypatch.setattr("rvggt_jax.ops.attention.compilable_platforms", lambda: ())
    with pytest.raises(tg.CompilerMissingError, match="cuDNN"):
        tg.check_compiler(tg.TARGETS["h100"])


def test_a_compiler_that_cannot_describe_the_target_says_what_to_install(monkeypatch):
    from jax.experimental import topologies

    def absent(*args, **kwargs):
        raise RuntimeError("Unknown backend: 'cuda' requested, but no platforms that are instances of cuda")

    monkeypatch.setattr(topologies, "get_topology_desc", absent)
    fresh = dataclasses.replace(tg.TARGETS["h200"], title="an H200 not described yet")  # not in the cache
    with pytest.raises(tg.CompilerMissingError, match=r"could not describe h200 .*Unknown backend.*rvggt-jax\[plan\]"):
        tg.target_device(fresh)


def test_the_triton_gemm_fallback_is_for_a_gpu_and_that_failure_alone():
    failure = "INTERNAL: Couldn't find output tile sizes that satisfy hlo: %dot.138 = f32[72,64]{1,0} dot(...)"
    assert tg.gemm_fallback(tg.TARGETS["h100"], failure) == {"xla_gpu_enable_triton_gemm": False}
    assert tg.gemm_fallback(tg.TARGETS["a100-80gb"], failure) is None  # it compiled without them already
    assert tg.gemm_fallback(tg.TARGETS["tpu-v6e"], failure) is None
    assert tg.gemm_fallback(tg.TARGETS["h200"], "INTERNAL: Mosaic failed to compile") is None
