"""The `rvggt` command line and what it runs: reconstruct, demo, convert, eval, finetune,
view, the in-memory pipeline and the output folder.
"""
