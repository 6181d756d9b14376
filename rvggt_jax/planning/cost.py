"""Cost model of the global blocks under a compression preset, from the configuration alone.

    report = rvggt_jax.cost_report(config, frames=64, height=168, width=224)
    report["predicted_speedup"]            # aggregator FLOPs: dense / preset
    report["layers"][i]["queries"], ["kv_slots"], ["kv_fixed"], ["kv_dynamic"], ...

It reads the same static plan (`compression.plan.layer_plan`) the compressed block
executes, so the query and K/V-slot counts here are the shapes the forward pass uses
(the cost model's tests check this against a traced forward).

What is counted (FLOPs, a multiply-add = 2, batch 1 unless `batch` is given):
  * linear layers: 2 * rows * in * out (QKV on all N tokens, but K/V on the kept tokens
    alone in K/V-only layers; the output projection on the N_m merged rows, the MLP on
    all N tokens);
  * attention matmuls: 2 * Nq * Nk * D_qk + 2 * Nq * Nk * D_v per head, with D_qk the
    folded head dimension (d + 1 padded, when the size column is used) and Nk the K/V
    *slots* (what is computed, empty slots included; of the data-dependent ones, the
    `kv_capacity` a layer attends with unless a sequence fills more: `kv_dynamic`, the
    bound in `kv_dynamic_bound`);
  * matching: 2 * (src x dst pairs) * C for the cosine similarities at the layers that
    compute a match (cached layers cost nothing);
  * frame blocks (always dense) and the global blocks; optionally the DINO patch embed.
Not counted: layer norms, softmax exponentials, RoPE, gathers/scatters of merging and
unmerging, argsort/top-k, the heads (unchanged by compression).
`predicted_speedup` = dense aggregator trunk FLOPs (24 frame + 24 global blocks) /
preset trunk FLOPs; `predicted_speedup_with_patch_embed` adds the DINO patch embed of
`config.dino` to both sides; `global_attention_ratio` compares the global attention
matmuls alone.
"""

from __future__ import annotations

from typing import Any

from rvggt_jax.compression.config import LayerKind
from rvggt_jax.compression.partition import Geometry
from rvggt_jax.compression.plan import layer_plan, padded_head_dim
from rvggt_jax.config import VGGTConfig


def _block_linear_flops(rows_qkv: int, rows_proj: int, rows_mlp: int, c: int, hidden: int,
                        rows_kv: int | None = None) -> int:
    """Q (and K, V: on `rows_kv` rows when given) projections, output projection, MLP."""
    rows_kv = rows_qkv if rows_kv is None else rows_kv
    return 2 * rows_qkv * c * c + 2 * rows_kv * c * 2 * c + 2 * rows_proj * c * c + 2 * rows_mlp * c * hidden * 2


def _attn_flops(nq: int, nk: int, heads: int, d_qk: int, d_v: int) -> int:
    return 2 * nq * nk * heads * (d_qk + d_v)


def patch_embed_flops(config: VGGTConfig, frames: int, h: int, w: int) -> int:
    """DINOv2 patch embed: patchify + `config.dino.depth` ViT blocks on 1 + registers + h*w
    tokens per frame (same dims as the aggregator)."""
    c = config.embed_dim
    t = h * w
    n = 1 + config.num_register_tokens + t
    hidden = int(c * config.dino.mlp_ratio)
    d = c // config.dino.num_heads
    per_frame = 2 * t * config.patch_size ** 2 * 3 * c
    per_frame += config.dino.depth * (_block_linear_flops(n, n, n, c, hidden)
                                      + _attn_flops(n, n, config.dino.num_heads, d, d))
    return frames * per_frame


def cost_report(config: VGGTConfig, frames: int, height: int, width: int, batch: int = 1) -> dict[str, Any]:
    """Per global layer: kind, query count, K/V slots (fixed / dynamic / duplicated), the
    expected number of filled slots, the folded head dim and the FLOPs (attention,
    matching, block total) for the configured preset and for dense; plus totals and the
    predicted speedups. See the module docstring for what is counted."""
    ps = config.patch_size
    if height % ps or width % ps:
        raise ValueError(f"height and width must be multiples of {ps}")
    h, w = height // ps, width // ps
    num_special = config.patch_start_idx
    c, heads = config.embed_dim, config.num_heads
    d = c // heads
    hidden = int(c * config.mlp_ratio)
    comp = config.compression
    geom = Geometry(frames, h, w, num_special)
    L, N = geom.per_frame, geom.tokens

    dense_global_attn = _attn_flops(N, N, heads, d, d)
    dense_global = _block_linear_flops(N, N, N, c, hidden) + dense_global_attn
    frame_block = _block_linear_flops(N, N, N, c, hidden) + frames * _attn_flops(L, L, heads, d, d)

    rows = []
    for layer in range(config.depth):
        plan = layer_plan(comp, layer, geom)
        if plan.kind == LayerKind.DENSE:
            q, kv, dqk = N, N, d
            attn = dense_global_attn
            lin = _block_linear_flops(N, N, N, c, hidden)
            fixed, dyn, dup, exp_fill = N, 0, 0, float(N)
        elif plan.kind == LayerKind.FRAME:
            q, kv, dqk = L, L, d
            attn = frames * _attn_flops(L, L, heads, d, d)
            lin = _block_linear_flops(N, N, N, c, hidden)
            fixed, dyn, dup, exp_fill = L, 0, 0, float(L)
        else:
            # (with duplicate_protected, the protected tokens' own queries attend too; the
            # dynamic K/V slots: the capacity a sequence attends with unless it fills more)
            q, kv = plan.n_query + plan.n_dup, plan.n_kv_cap
            dqk = padded_head_dim(d, plan.size_column, comp.head_pad_multiple)
            dv = d if comp.head_pad_multiple == 1 or not plan.size_column else dqk
            attn = _attn_flops(q, kv, heads, dqk, dv)
            # K/V-only layers project K and V for the kept tokens alone
            lin = _block_linear_flops(N, q, N, c, hidden, rows_kv=kv if plan.kind == LayerKind.KV else N)
            fixed, dyn, dup = plan.n_fixed, plan.n_dyn_cap, plan.n_dup
            exp_fill = plan.n_fixed + plan.expected_dyn + plan.expected_dup
        match = 2 * plan.match_pairs * c if plan.match == "compute" else 0
        total = attn + lin + match
        rows.append(dict(
            layer=layer, kind=plan.kind, tile=plan.tile, merged=plan.r, queries=q, kv_slots=kv, kv_fixed=fixed,
            kv_dynamic=dyn, kv_dynamic_bound=plan.n_dyn, kv_duplicates=dup, kv_filled_expected=exp_fill,
            head_dim_qk=dqk,
            match=plan.match, match_key=plan.match_key,
            attention_flops=batch * attn, match_flops=batch * match, flops=batch * total,
            dense_attention_flops=batch * dense_global_attn, dense_flops=batch * dense_global,
            attention_ratio=attn / dense_global_attn,
        ))

    glob = sum(r["flops"] for r in rows)
    glob_dense = batch * dense_global * config.depth
    frames_total = batch * frame_block * config.depth
    pe = batch * patch_embed_flops(config, frames, h, w)
    attn_sum = sum(r["attention_flops"] for r in rows)
    return dict(
        preset=comp.name, frames=frames, grid=(h, w), tokens=N, batch=batch, layers=rows,
        global_attention_flops=attn_sum, dense_global_attention_flops=batch * dense_global_attn * config.depth,
        global_attention_ratio=attn_sum / (batch * dense_global_attn * config.depth),
        match_flops=sum(r["match_flops"] for r in rows),
        global_flops=glob, dense_global_flops=glob_dense, frame_block_flops=frames_total,
        aggregator_flops=glob + frames_total, dense_aggregator_flops=glob_dense + frames_total,
        patch_embed_flops=pe,
        predicted_speedup=(glob_dense + frames_total) / (glob + frames_total),
        predicted_speedup_with_patch_embed=(glob_dense + frames_total + pe) / (glob + frames_total + pe),
        kv_fill_expected=(sum(r["kv_filled_expected"] for r in rows) / max(1, sum(r["kv_slots"] for r in rows))),
    )
