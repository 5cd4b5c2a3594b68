"""Many scans at once, above the pipeline (imports it, never evaluators, commands or training).

- :mod:`~dit_jax.scenes.series`: a series of scans registered one after another.
- :mod:`~dit_jax.scenes.scene`: a whole scene: which pairs to register, the pose graph, the placed scans.
"""
