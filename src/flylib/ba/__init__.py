"""Bundle-adjustment internals: parameter grammar, frame sampling, the JAX/scipy solver.

The public entry points live in :mod:`flylib.bundle_adjustment`.
"""
