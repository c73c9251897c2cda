"""Engine: the public propagation, covariance, filter-update and preintegration functions,
their input checks, the ``jax.vmap`` routing and the dispatch table that picks a kernel.
Imports the kernels, schemes and geometry.
"""
