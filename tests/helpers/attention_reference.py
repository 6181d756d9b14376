"""The float64 attention reference of the attention tests."""

from __future__ import annotations

import math

import numpy as np


def reference_attention(q, k, v, bias=None):
    """softmax(q k^T / sqrt(d) + bias) v in float64 numpy, upstream's [B, H, N, D] layout."""
    q, k, v = (np.asarray(a, np.float64).transpose(0, 2, 1, 3) for a in (q, k, v))
    logits = q @ k.transpose(0, 1, 3, 2) / math.sqrt(q.shape[-1])
    if bias is not None:
        logits = logits + np.asarray(bias, np.float64)
    p = np.exp(logits - logits.max(-1, keepdims=True))
    return ((p / p.sum(-1, keepdims=True)) @ v).transpose(0, 2, 1, 3)
