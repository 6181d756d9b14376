"""The kernels of the attention op (`rvggt_jax.ops.attention`), one module each: the
cache-blocked kernel (`blocked`) and the fused ones with the key bias folded into the
operands (`fused`: cuDNN flash attention, and its plain XLA form)."""
