"""The verdict (the pipeline's last stage): whether a registration is trusted, and the level a user reads.

The whole rule lives here, its thresholds in :class:`~dit_jax.pipeline.settings.InferenceSettings`:

* **Registered by the network** (:func:`judge`). Under the agreement rule the pair is registered both ways,
  source onto target and target onto source; the result is trusted where the two rotations are inverse
  within ``max_disagreement_network`` degrees (``max_disagreement_icp`` after a refinement). Under the
  fitness rule it is trusted where its fitness reaches ``min_fitness``.
* **Registered by local features** (:func:`judge_features`): trusted where both directions found one motion
  (within ``max_disagreement_features`` degrees and ``max_offset_features`` point spacings), neither with a
  rival motion backed by more than ``max_rival_features`` of its matches nor a turned twin that lays more
  than ``max_twin_features`` of its points (:func:`features_agree`).
* **The level** (:func:`level`): "trusted"; else "unconfirmed" where the validation results whose two
  directions agreed as closely (the result's :class:`Band`) were mostly right (``unconfirmed_min_right``);
  else "probably wrong".
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from dit_jax.geometry import rigid
from dit_jax.pipeline.settings import InferenceSettings

if TYPE_CHECKING:
    from dit_jax.features.matching import FeatureEstimate

#: A :class:`Band` is quoted only where at least this many validation results fell in it.
MIN_BAND_PAIRS = 10


class Band(NamedTuple):
    """A band of agreement, (``low``, ``high``] degrees (``high`` None: unbounded), and how many validation
    results fell in it (``pairs``) and how many of those were within 5 degrees of the truth (``right``)."""

    low: float
    high: float | None
    pairs: int
    right: int


class Verdict(NamedTuple):
    """The judgement of one result: whether the rule ``trusted`` it, the rule's ``threshold`` (degrees of
    disagreement, or a share of fitness), the two directions' ``agreement`` (degrees; NaN under the fitness
    rule) and the validation :class:`Band` it falls in (None where none is quoted)."""

    trusted: bool
    threshold: float
    agreement: float
    band: Band | None


def judge(
    settings: InferenceSettings,
    refine: str,
    fitness: float,
    forward_rotation: np.ndarray,
    backward_rotation: np.ndarray | None,
) -> Verdict:
    """The :class:`Verdict` of a result the network found (refined by ``refine``, "none" for none): the agreement
    rule trusts it where ``forward_rotation`` (3, 3), source onto target, and ``backward_rotation``, target onto
    source, are within ``settings.max_disagreement(refine)`` degrees of inverse; the fitness rule where its
    ``fitness`` reaches ``settings.min_fitness``."""
    if settings.verdict_rule == "agreement":
        threshold = settings.max_disagreement(refine)
        agreement = rigid.rotation_angle_deg(forward_rotation @ backward_rotation)
        band = agreement_band(settings.agreement_bands(refine), agreement)
        return Verdict(agreement <= threshold, threshold, agreement, band)
    return Verdict(fitness >= settings.min_fitness, settings.min_fitness, float("nan"), None)


def features_agree(
    found: FeatureEstimate,
    max_degrees: float,
    max_spacings: float,
    max_rival: float = np.inf,
    max_twin: float = np.inf,
) -> bool:
    """Whether the two directions of ``found`` settle a pair: both found a motion, the two within ``max_degrees``
    and ``max_spacings``, each with no rival backed by more than ``max_rival`` of its matches and no turned twin
    laying more than ``max_twin`` of its points."""
    return bool(
        found.disagreement <= max_degrees
        and found.offset <= max_spacings
        and min(found.inliers) > 0
        and max(found.rival) <= max_rival
        and max(found.twin) <= max_twin
    )


def judge_features(found: FeatureEstimate, settings: InferenceSettings) -> Verdict:
    """The :class:`Verdict` of a result local features found: :func:`features_agree` at the settings'
    thresholds; no band is quoted (a result it does not trust is "probably wrong")."""
    trusted = features_agree(
        found,
        settings.max_disagreement_features,
        settings.max_offset_features,
        settings.max_rival_features,
        settings.max_twin_features,
    )
    return Verdict(trusted, settings.max_disagreement_features, found.disagreement, None)


def level(trusted: bool, band: Sequence | None, min_right: float) -> str:
    """The level of :data:`dit_jax.pipeline.result.VERDICT_LEVELS` of a result: "trusted" where the verdict trusts it;
    else "unconfirmed" where its agreement ``band`` (:class:`Band`) holds at least ``min_right`` of right
    validation results, and "probably wrong" where it holds fewer or was not measured (no band, too few
    results in it, or the fitness rule, which records none)."""
    if trusted:
        return "trusted"
    if band is not None and band[2] > 0 and band[3] / band[2] >= min_right:
        return "unconfirmed"
    return "probably wrong"


def agreement_band(bands: Sequence | None, agreement: float) -> Band | None:
    """The :class:`Band` of ``bands`` (((upper or None, pairs, right), ...), increasing) that ``agreement``
    (degrees) falls in; None without bands or agreement, or for a band of too few pairs."""
    if not bands or not np.isfinite(agreement):
        return None
    low = 0.0
    for high, pairs, right in bands:
        if high is None or agreement <= high:
            return Band(low, high, int(pairs), int(right)) if pairs >= MIN_BAND_PAIRS else None
        low = high
    return None
