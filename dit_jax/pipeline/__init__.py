"""The registration pipeline: settings, its stages and the :class:`~dit_jax.pipeline.result.Result` they make.

Imports the layers below it (:mod:`dit_jax.geometry`, :mod:`dit_jax.io`, :mod:`dit_jax.network`,
:mod:`dit_jax.features`, :mod:`dit_jax.pictures`), never scenes, evaluators, commands or training.

- :mod:`~dit_jax.pipeline.registration`: :func:`~dit_jax.pipeline.registration.load` and the ``Registrar``
  (public as ``from dit_jax import registration``).
- :mod:`~dit_jax.pipeline.stages`: ``register_pairs``, the stages by name: sampling, the network both ways,
  refinement, the verdict.
- :mod:`~dit_jax.pipeline.settings`, :mod:`~dit_jax.pipeline.sampling`,
  :mod:`~dit_jax.pipeline.network_stage`, :mod:`~dit_jax.pipeline.refinement`,
  :mod:`~dit_jax.pipeline.verdict`, :mod:`~dit_jax.pipeline.result`: one stage or record each.
"""
