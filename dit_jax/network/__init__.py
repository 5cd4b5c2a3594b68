"""The paper's network and its weights in and out; imports :mod:`dit_jax.geometry` only.

- :mod:`~dit_jax.network.configs`: :class:`~dit_jax.network.configs.DITConfig` and the named sizes.
- :mod:`~dit_jax.network.layers`, :mod:`~dit_jax.network.pse`, :mod:`~dit_jax.network.pft`,
  :mod:`~dit_jax.network.gmcce`, :mod:`~dit_jax.network.head`: attention blocks, the point structure encoder
  (LFI), the point feature transformer (encoder/decoder stacks), the triangle-descriptor confidence (GMCCE) and
  the head that turns matches into a motion.
- :mod:`~dit_jax.network.model`: DIT itself (``init``, ``forward``, ``register``); :mod:`~dit_jax.network.losses`.
- :mod:`~dit_jax.network.checkpoint`, :mod:`~dit_jax.network.convert`, :mod:`~dit_jax.network.torch_pickle`,
  :mod:`~dit_jax.network.reference_check`: orbax checkpoints, the authors' PyTorch weights, and the check
  against their recorded activations; :mod:`~dit_jax.network.compile_cache`: compiled programs kept on disk.
- ``weights/``: the weights that ship with the package.
"""
