"""XLA:CPU's plan (compile only, nothing runs) of the gradient of one attention call of the
blocked kernel: its custom VJP (flash attention's backward, O(N d)) against JAX's
autodiff of the same forward loop (what the kernel had before issue 25: every query
block's softmax weights kept, O(N^2)).

    python benchmarks/bench_attention_grad.py                  # the table of docs/history/training.md
    python benchmarks/bench_attention_grad.py --tokens 2048 8192 --heads 1 --dtype float32

q, k, v [1, N, H, 64] and a key bias [1, N] (a global layer: N = frames x tokens per
frame; VGGT-1B at 24 frames of 518 x 518 is 24 x 1,374 = 32,976 tokens, 16 heads); the
loss is the sum of the output, the gradient taken to q, k, v and the bias.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rvggt_jax.ops import attention as attn  # noqa: E402
from rvggt_jax.ops.kernels import blocked  # noqa: E402


def temp_bytes(n: int, heads: int, dtype, backward: str, block_bytes: int) -> tuple[int, float]:
    """(XLA's temporaries in bytes, compile seconds) of jit(grad) of one attention call."""
    args = [jax.ShapeDtypeStruct((1, n, heads, 64), dtype)] * 3 + [jax.ShapeDtypeStruct((1, n), jnp.float32)]
    scale = 1 / 8

    if backward == "custom_vjp":
        def fn(q, k, v, b):
            return attn.attention(q, k, v, b, implementation="blocked", block_bytes=block_bytes)
    else:  # autodiff of the forward loop (the kernel without its custom VJP)
        def fn(q, k, v, b):
            return blocked._forward(q, k, v, b, scale, block_bytes, None, False)[0]

    t0 = time.perf_counter()
    grad = jax.jit(jax.grad(lambda *a: jnp.sum(fn(*a).astype(jnp.float32)), (0, 1, 2, 3)))
    compiled = grad.lower(*args).compile()
    return compiled.memory_analysis().temp_size_in_bytes, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tokens", type=int, nargs="+", default=[2048, 8192, 32976])
    ap.add_argument("--heads", type=int, default=16)
    ap.add_argument("--dtype", default="bfloat16", choices=("float32", "bfloat16"))
    ap.add_argument("--block-bytes", type=int, default=blocked.LOGITS_BLOCK_BYTES)
    ap.add_argument("--backward", nargs="+", default=["autodiff", "custom_vjp"], choices=("autodiff", "custom_vjp"))
    args = ap.parse_args()
    dtype = jnp.dtype(args.dtype)
    print("| N | heads | dtype | backward | temporaries MB | compile s |\n|---:|---:|---|---|---:|---:|")
    for n in args.tokens:
        for backward in args.backward:
            t, s = temp_bytes(n, args.heads, dtype, backward, args.block_bytes)
            print(f"| {n} | {args.heads} | {dtype.name} | {backward} | {t / 2**20:.1f} | {s:.1f} |", flush=True)


if __name__ == "__main__":
    main()
