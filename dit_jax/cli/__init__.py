"""The console commands, the top layer beside the evaluators: they parse flags and call the pipeline and scenes.

- :mod:`~dit_jax.cli.register`: ``dit-register`` (one pair), with :mod:`~dit_jax.cli.pair_list` for ``--pairs``.
- :mod:`~dit_jax.cli.series`: ``dit-register-series``; :mod:`~dit_jax.cli.scene`: ``dit-register-scene``.
- :mod:`~dit_jax.cli.files`: what they share: reading clouds, checking outputs, their flags and exit.
- :mod:`~dit_jax.cli.results_log`: the results log a list appends to (and resumes from).
"""
