"""Evaluation by kind: synthetic pairs (:mod:`.synthetic`), real scans (:mod:`.scans`), whole scenes
(:mod:`.scenes`), the rotation range (:mod:`.sweep`) and descriptors' matches (:mod:`.descriptors`); :mod:`.report` writes their tables and plots, :mod:`.common` holds what they share. Every DIT
result comes from the registration pipeline (:mod:`dit_jax.pipeline.stages`)."""

from dit_jax.evaluators.common import METHOD_DIT, METHOD_DIT_ICP, METHOD_PIPELINE, Estimates, rescore_agreement, run_dit  # noqa: F401
from dit_jax.evaluators.scans import evaluate_scans  # noqa: F401
from dit_jax.evaluators.scenes import evaluate_scenes  # noqa: F401
from dit_jax.evaluators.sweep import angle_sweep  # noqa: F401
from dit_jax.evaluators.synthetic import evaluate  # noqa: F401
