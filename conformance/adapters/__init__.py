"""Built-in adapters of the conformance runner ([CF-12]): reference (NumPy) and jax."""
