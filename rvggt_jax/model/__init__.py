"""The VGGT model as pure functions over the parameter pytree: patch embed, aggregator,
heads, the whole forward (`forward.rvggt_forward`), the Flax modules and initialisers.
"""
