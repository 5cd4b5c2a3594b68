"""The verdict (:mod:`dit_jax.pipeline.verdict`): the network's agreement or fitness rule, the features' rule, and the
level a user reads."""

import dataclasses

import numpy as np
import pytest

from dit_jax.pipeline import verdict
from dit_jax.pipeline.result import VERDICT_LEVELS
from dit_jax.pipeline.settings import InferenceSettings


def test_the_verdict_stage_judges_by_agreement_or_fitness():
    quarter_turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    settings = InferenceSettings(
        max_disagreement_network=1.0, max_disagreement_icp=100.0, agreement_bands_icp=[[10.0, 50, 45], [None, 40, 2]]
    )
    trusted, threshold, agreement, band = verdict.judge(settings, "none", 0.0, quarter_turn, quarter_turn.T)
    assert trusted and threshold == 1.0 and agreement == pytest.approx(0.0, abs=1e-6) and band is None
    trusted, threshold, agreement, band = verdict.judge(settings, "icp", 0.0, quarter_turn, quarter_turn)
    assert not trusted and threshold == 100.0 and agreement == pytest.approx(180.0) and band == (10.0, None, 40, 2)
    fitness = settings.replace(verdict_rule="fitness", min_fitness=0.6)
    assert verdict.judge(fitness, "icp", 0.7, quarter_turn, None)[:2] == (True, 0.6)
    assert not verdict.judge(fitness, "icp", 0.5, quarter_turn, None)[0]
    assert np.isnan(verdict.judge(fitness, "icp", 0.5, quarter_turn, None)[2])


def test_a_result_not_trusted_is_unconfirmed_only_where_its_band_was_mostly_right():
    band = lambda pairs, right: (1.0, 2.0, pairs, right)
    assert verdict.level(True, None, 0.5) == "trusted"
    assert verdict.level(False, band(20, 10), 0.5) == "unconfirmed"  # half right: mostly enough
    assert verdict.level(False, band(20, 9), 0.5) == "probably wrong"
    assert verdict.level(False, None, 0.5) == "probably wrong"  # no evidence either way
    assert verdict.level(False, band(20, 19), 0.99) == "probably wrong"
    assert VERDICT_LEVELS == ("trusted", "unconfirmed", "probably wrong")


def test_agreement_bands_are_quoted_only_from_enough_results():
    bands = ((1.0, 50, 49), (10.0, 5, 3), (None, 40, 2))
    assert verdict.agreement_band(bands, 0.5) == verdict.Band(0.0, 1.0, 50, 49)
    assert verdict.agreement_band(bands, 5.0) is None  # a band of 5 results: not quoted
    assert verdict.agreement_band(bands, 90.0) == (10.0, None, 40, 2)
    assert verdict.agreement_band(bands, float("nan")) is None and verdict.agreement_band((), 1.0) is None


@dataclasses.dataclass
class _Found:
    """The evidence of :class:`dit_jax.features.matching.FeatureEstimate` that the features' rule reads."""

    disagreement: float = 0.2
    offset: float = 0.5
    inliers: tuple = (40, 35)
    rival: tuple = (0.1, 0.2)
    twin: tuple = (0.3, 0.4)


def test_the_features_settle_a_pair_only_where_every_bound_holds():
    settings = InferenceSettings(max_rival_features=0.5, max_twin_features=0.8)
    judged = verdict.judge_features(_Found(), settings)
    assert judged.trusted and judged.threshold == settings.max_disagreement_features and judged.band is None
    for broken in (
        _Found(disagreement=settings.max_disagreement_features + 0.1),
        _Found(offset=settings.max_offset_features + 0.1),
        _Found(inliers=(40, 0)),  # one direction found nothing
        _Found(rival=(0.1, 0.6)),
        _Found(twin=(0.9, 0.1)),
    ):
        assert not verdict.judge_features(broken, settings).trusted, broken
    assert verdict.features_agree(_Found(rival=(0.1, 0.6)), 1.0, 2.0), "no rival bound unless one is given"
    assert verdict.level(False, None, settings.unconfirmed_min_right) == "probably wrong"
