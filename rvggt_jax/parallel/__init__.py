"""Many devices: the forward split over devices by frames (`sharded`: `jax.shard_map` over a
mesh axis "frames"), and the train step over a ("data", "frames") mesh with optional FSDP
(`train`).
"""
