"""Tolerances that more than one test module holds the model to."""

# The track head's iteration 4 vs io.safetensors (tests/model/test_track_head.py, and
# through the whole forward in tests/model/test_forward.py): about twice upstream's own
# spread under 1e-7 input noise (the reasoning: test_track_head.py's docstring).
FINAL_ITER_RTOL = {"track": 6e-3, "vis": 9e-2, "conf": 2e-2}
