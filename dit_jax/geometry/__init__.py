"""Classical geometry, the package's lowest layer: it imports nothing else of dit_jax.

- :mod:`~dit_jax.geometry.rigid`: JAX nearest neighbours, rigid motions and weighted Procrustes (the paper's
  SVD step), acting on one cloud; ``jax.vmap`` them for batches.
- :mod:`~dit_jax.geometry.icp`: ICP and its trimmed fits on NumPy clouds, searched starts, generalized ICP,
  point spacing and normals.
"""
