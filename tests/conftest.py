import jax

# float64 everywhere (SPEC section 1); tlsjax sets it too, but tests may import jax first.
jax.config.update("jax_enable_x64", True)
