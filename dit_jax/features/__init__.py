"""Registration by local features: what each keypoint's neighbourhood looks like, and the motion the matches back.

- :mod:`~dit_jax.features.descriptors`: what each keypoint of a cloud's voxel grid is matched by: FPFH at one
  radius (the default), or FPFH at several radii, square-rooted and joined, or the learned descriptor.
- :mod:`~dit_jax.features.network`: the learned descriptor, a small Flax network over the joined histograms,
  its weights in and out (trained by :mod:`dit_jax.training.descriptor`).
- :mod:`~dit_jax.features.compatibility`: the compatibility-graph estimator, matches to ranked motions (JAX).
- :mod:`~dit_jax.features.matching`: both directions of a pair, from clouds to refined motions and the evidence
  the verdict reads.

Imports only :mod:`dit_jax.geometry.rigid` and :mod:`dit_jax.geometry.icp` from the package, never the network or the pipeline.
"""
