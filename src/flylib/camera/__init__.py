"""The camera, one module per role.

model
    The camera model's formulas (Rodrigues both ways, ``K``, OpenCV distortion and its
    fixed-point inverse, projection, the DLT), written once for any array module, and
    their NumPy bindings; imports no JAX.
jax_model
    The same formulas bound to ``jax.numpy`` (float64, CPU, jit/grad-able) and the bulk
    DLT; importing it sets JAX to float64 on the CPU with the persistent compile cache.
rig
    ``Camera`` and ``CameraGroup``: cameras resolved from their specs (orbit or explicit
    extrinsics, intrinsics), stacked views, projection, triangulation, back-projection.

The package imports none of them, so code that needs only ``model`` or ``rig`` never
loads JAX.
"""
