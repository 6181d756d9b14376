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

`ring_exchange` counts, from the same plans, what each device sends in each global layer
when the frames are split over devices (`sharded_forward`, docs/sharding.md).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

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


FLOAT32 = INT32 = 4  # the residual stream, the group sums, the size bias; the match's indices


def device_attention_flops(config: VGGTConfig, frames: int, height: int, width: int, devices: int,
                           batch: int = 1) -> list[int]:
    """The global layers' attention FLOPs one device computes when `frames` frames are split
    over `devices` (`sharded_forward`), per layer; on one device `cost_report`'s. Over
    devices the keys differ from one device's: a merging layer's ring carries every merged
    row (R per device, R = ceil((N_m [+ 1]) / D); K/V downsampling masks the rows it does
    not keep instead of dropping them: as many keys as queries), the size bias always
    folded into the head dimension, and the protected tokens' own queries and keys
    (`n_dup_all`) on every device; a K/V-downsampled layer attends to all its dynamic
    slots; a dense layer's keys are the padded sequence."""
    rep = cost_report(config, frames, height, width, batch)
    if devices == 1:
        return [r["attention_flops"] for r in rep["layers"]]
    ps = config.patch_size
    h, w = height // ps, width // ps
    comp, heads, d = config.compression, config.num_heads, config.embed_dim // config.num_heads
    geom = Geometry(frames, h, w, config.patch_start_idx)
    local = math.ceil(frames / devices)
    rows_local = local * geom.per_frame
    out = []
    for r in rep["layers"]:
        plan = layer_plan(comp, r["layer"], geom)
        if plan.kind == LayerKind.DENSE:
            flops = _attn_flops(rows_local, rows_local * devices, heads, d, d)
        elif plan.kind == LayerKind.FRAME:
            flops = local * _attn_flops(geom.per_frame, geom.per_frame, heads, d, d)
        elif plan.kind == LayerKind.KV:
            dqk = padded_head_dim(d, plan.size_column, comp.head_pad_multiple)
            dv = d if comp.head_pad_multiple == 1 or not plan.size_column else dqk
            flops = _attn_flops(rows_local, plan.n_kv, heads, dqk, dv)
        else:
            rows = math.ceil((plan.n_query + int(local * devices > frames)) / devices)
            dqk = padded_head_dim(d, True, comp.head_pad_multiple)
            dv = d if comp.head_pad_multiple == 1 else dqk
            flops = _attn_flops(rows + plan.n_dup_all, rows * devices + plan.n_dup_all, heads, dqk, dv)
        out.append(batch * flops)
    return out


def _most_per_device(positions: np.ndarray, rows_per_device: int, devices: int) -> int:
    """The most of the static token positions (ascending) one device holds, as
    `FrameShards.local_positions` pads every device's share to it (at least 1)."""
    counts = np.bincount(np.asarray(positions).reshape(-1) // rows_per_device, minlength=devices)
    return max(1, int(counts.max()) if counts.size else 1)


def ring_exchange(config: VGGTConfig, frames: int, height: int, width: int, devices: int,
                  batch: int = 1) -> list[dict[str, Any]]:
    """What each device sends in each global layer when `frames` frames are split over
    `devices` devices (`sharded_forward`; it receives as many bytes: every exchange is a
    ring step, or an all-gather or all-reduce, the same each way). One dict per global
    layer: "layer", "kind", "parts" {what: bytes}, "bytes" (their sum); all 0 on one
    device. Counted from the layer's static plan (`compression.plan.layer_plan`) as the
    code exchanges it (`ops/ring.py`, `ops/shards.py`, `compression/merged_layer.py`),
    batch `batch`, D = devices, R = ceil((N_m [+ 1 with padding frames]) / D) merged rows
    a device holds, G = `merge_head_groups`, C the width, b the compute dtype's bytes:

      dense      "K/V": D - 1 ring steps of this device's K and V [B, S/D x P, C] in the
                 compute dtype (and the float32 padding mask when D does not divide S);
      frame      nothing;
      kv         "kept rows": the kept tokens' float32 residual rows [B, N_kv, C] (all
                 slots, the dynamic ones too) summed over devices (a psum with one non-zero
                 term): a ring all-reduce sends 2 (D - 1) / D of them;
      merging    "Q/K/V sums": the float32 group sums of q, k and v reduce-scattered around
                 the ring, 3 (D - 1) R C x 4; "K/V": the merged K and V (every merged row,
                 those a layer does not keep as keys masked: K/V downsampling does not
                 shorten the ring) and their float32 size bias, per head group,
                 (D - 1) R (2 C b + 4 G); "output rows": the projected merged rows
                 (D - 1) R C b, for the unmerge; "matching" (layers that compute their
                 match): the dst unit rows [B, N_dst/D, C] (b) and their float32 ranks around
                 the ring and the src scores (float32) and matches (int32) all-gathered;
                 "protected rows": the protected tokens' float32 rows (all-reduced) per
                 head group where the plan takes their own rows (`n_dup_all`,
                 `protected_rows`).
    Not counted: the camera head's and tracker's all-gathers (once per forward, not per
    layer), the padding frames' share of a frame count D does not divide."""
    if devices < 1 or batch < 1:
        raise ValueError(f"devices and batch must be at least 1; got {devices}, {batch}")
    ps = config.patch_size
    if height % ps or width % ps:
        raise ValueError(f"height and width must be multiples of {ps}")
    h, w = height // ps, width // ps
    comp, c = config.compression, config.embed_dim
    item = config.compute_dtype.itemsize
    geom = Geometry(frames, h, w, config.patch_start_idx)
    per_frame = geom.per_frame
    local = math.ceil(frames / devices)
    padded = local * devices > frames
    rows_per_device = local * per_frame
    steps = devices - 1  # ring steps: every other device's share passes once
    allreduce = 2 * (devices - 1) / devices  # of the array, sent by each device (a ring all-reduce)
    groups = min(comp.merge_head_groups, config.num_heads)  # `merged_layer.head_groups`
    out = []
    for layer in range(config.depth):
        plan = layer_plan(comp, layer, geom)
        parts: dict[str, float] = {}
        if devices > 1 and plan.kind == LayerKind.DENSE:
            parts["K/V"] = steps * batch * rows_per_device * (2 * c * item + (FLOAT32 if padded else 0))
        elif devices > 1 and plan.kind == LayerKind.KV:
            parts["kept rows"] = allreduce * batch * plan.n_kv * c * FLOAT32
        elif devices > 1 and plan.kind == LayerKind.MERGE:
            rows = math.ceil((plan.n_query + int(padded)) / devices)
            if plan.match == "compute":
                part = plan.partition
                if plan.scope == "sequence":
                    src = part.src_pos if plan.matched_src is None else part.src_pos[plan.matched_src]
                    dst = _most_per_device(part.dst_pos, rows_per_device, devices)
                    parts["matching"] = (steps * (batch * dst * c * item + dst * FLOAT32)
                                         + steps * batch * _most_per_device(src, rows_per_device, devices)
                                         * (FLOAT32 + INT32))
                else:  # each frame's src against its dst where it lives: the results all-gathered
                    frames_held = _most_per_device(part.src_pos_f[:, 0], rows_per_device, devices)
                    parts["matching"] = steps * batch * frames_held * part.src_pos_f.shape[1] * (FLOAT32 + INT32)
            parts["Q/K/V sums"] = 3 * steps * batch * rows * c * FLOAT32
            parts["K/V"] = steps * batch * rows * (2 * c * item + FLOAT32 * groups)
            own = 2 * bool(plan.n_dup_all) + int(plan.protected_rows)  # rows_kv + queries; own_qkv
            if own:
                protected = plan.n_dup_all or plan.n_unm
                parts["protected rows"] = groups * own * allreduce * batch * protected * c * FLOAT32
            parts["output rows"] = steps * batch * rows * c * item
        out.append(dict(layer=layer, kind=plan.kind, parts=parts, bytes=sum(parts.values())))
    return out
