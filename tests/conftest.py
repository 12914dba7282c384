import jax

# Identification runs in float64; the library itself never flips this on import.
jax.config.update("jax_enable_x64", True)
