"""Datasets: the shapes and scans the network trains and is measured on. Imports :mod:`dit_jax.io` only.

- :mod:`~dit_jax.data.shapes`: ModelNet40 (the h5 layout) and the embedded set, through TFDS.
- :mod:`~dit_jax.data.pairs`: registration pairs made from shapes (the paper's settings and settings as real
  data has them); :mod:`~dit_jax.data.views`: scan-like views and samplers; :mod:`~dit_jax.data.mixed`:
  batches over several settings; :mod:`~dit_jax.data.prefetch`: batches made ahead in a thread.
- :mod:`~dit_jax.data.scans`: folders of real scans with known poses (3DMatch lists, Stanford ``.conf``,
  KITTI poses) and their benchmarks' criteria.
"""
