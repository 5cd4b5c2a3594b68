"""Pictures and pages of registrations: Matplotlib figures and HTML views a browser turns.

Below the pipeline (results draw themselves with it); imports :mod:`dit_jax.geometry` and :mod:`dit_jax.io`.

- :mod:`~dit_jax.pictures.plotting`: PNG figures of a pair or a series.
- :mod:`~dit_jax.pictures.view`: self-contained HTML pages.
"""
