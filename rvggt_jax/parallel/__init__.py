"""The forward split over devices by frames (`jax.shard_map` over a mesh axis "frames").
"""
