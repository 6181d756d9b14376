"""The names of the attention kernels (`VGGTConfig.attention`, `ops.attention`'s
`implementation`): a leaf module, so that the configuration can check a name without
loading the kernels.

  "auto"       the kernel of the platform being compiled for (`ops.attention.kernel_for`)
  "blocked"    the cache-blocked kernel (any platform, any dtype; memory bounded)
  "cudnn"      cuDNN's flash attention (NVIDIA GPUs, bfloat16/float16 only)
  "xla"        `jax.nn.dot_product_attention`'s plain XLA form (forms all logits: checks)
  "tpu_flash"  the Pallas TPU flash attention kernel (TPUs)
"""

KERNELS = ("auto", "blocked", "cudnn", "xla", "tpu_flash")

# kernels that take only 16-bit floating operands
HALF_ONLY = ("cudnn",)
