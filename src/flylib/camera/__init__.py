"""The camera, one module per role (the package imports none, so ``model`` or ``rig`` alone
never loads JAX).

- ``model``: the formulas (Rodrigues both ways, ``K``, OpenCV distortion and its fixed-point
  inverse, projection, the DLT), written once for any array module, and their NumPy bindings;
- ``jax_model``: the same bound to ``jax.numpy`` (jit/grad-able) and the bulk DLT; importing
  it sets JAX to float64 on the CPU with the persistent compile cache;
- ``rig``: ``Camera`` and ``CameraGroup`` resolved from their specs (orbit or explicit
  extrinsics, intrinsics): stacked views, projection, triangulation, back-projection."""
