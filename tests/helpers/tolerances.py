"""Tolerances that more than one test module holds the model to."""

# The track head's iteration 4 vs io.safetensors (tests/model/test_track_head.py, and
# through the whole forward in tests/model/test_forward.py): about twice upstream's own
# spread under 1e-7 input noise (the reasoning: test_track_head.py's docstring).
FINAL_ITER_RTOL = {"track": 6e-3, "vis": 9e-2, "conf": 2e-2}

# Upstream's own bfloat16 deviation from its float32 outputs (max |bf16 - f32| / max |f32|),
# CPU autocast on the tiny checkpoint (`benchmarks/upstream_bf16.py`, docs/benchmarks.md
# "Upstream's own bf16 deviation"): a bf16 mode passes within twice it
UPSTREAM_BF16 = {"aggregated": 1.1e-2, "pose_enc": 1.6e-2, "depth": 7.0e-3, "depth_conf": 7.9e-3,
                 "world_points": 1.9e-2, "world_points_conf": 5.9e-3}
