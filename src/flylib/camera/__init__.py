"""The camera, one module per role: ``model`` (the formulas, written once for any array module, and
their NumPy bindings), ``jax_model`` (the same bound to ``jax.numpy``; importing it sets JAX to
float64 on the CPU with the persistent compile cache) and ``rig`` (``Camera`` and ``CameraGroup``
resolved from their specs). The package imports none, so ``model`` or ``rig`` alone never loads
JAX."""
