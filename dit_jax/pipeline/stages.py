"""The registration pipeline: every registration in dit-jax runs through :func:`register_pairs`.

A batch of pairs goes through these stages, each a function that takes and returns :class:`Pair` records:

0. :func:`by_features` (where :attr:`InferenceSettings.feature_candidate` says so; dense scans by default):
   local features register the source onto the target and the target onto the source
   (:func:`dit_jax.features.matching.register_both_ways`). Such a pair's result is theirs (:func:`features_result`),
   and the network does not run: on the shared room scans it registered no pair the features missed, and
   its confirmations of their motions were right less often than the features' own agreement
   (docs/verdict.md);
1. :func:`sampled`: the other pairs' clouds resampled to the settings' point count and moved into the unit
   sphere (:func:`dit_jax.pipeline.sampling.sample_and_normalise`);
2. :func:`estimated`: the network's estimates, both ways under the agreement verdict
   (:func:`dit_jax.pipeline.network_stage.estimate_pairs`);
3. the refinement on the full clouds (:func:`dit_jax.pipeline.refinement.refine_pair`), in :func:`network_result`;
4. the verdict (:mod:`dit_jax.pipeline.verdict`): trusted, unconfirmed or probably wrong.

:meth:`dit_jax.pipeline.registration.Registrar.register` is this pipeline on a batch of one; evaluate.py, the
calibration of the verdict (`tools/calibrate.py`) and the benchmarks call it on many pairs.
Every setting of the pipeline lives in one frozen :class:`~dit_jax.pipeline.settings.InferenceSettings`, saved with the
weights.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from dit_jax.network.configs import DITConfig
from dit_jax.pipeline import network_stage, refinement, verdict
from dit_jax.pipeline.network_stage import PairEstimate
from dit_jax.pipeline.refinement import Motion
from dit_jax.pipeline.result import Result
from dit_jax.pipeline.sampling import Normalised, check_cloud, check_pair, sample_and_normalise
from dit_jax.pipeline.settings import InferenceSettings

if TYPE_CHECKING:
    from dit_jax.features.matching import FeatureEstimate

#: A result found without the network counts a source point as landing on the target within this many
#: point spacings of a target point (its ``confidence`` and ``inlier_ratio``).
CANDIDATE_OVERLAP = 2.0


class Pair(NamedTuple):
    """One pair on its way through the stages: its checked clouds, src (N, 3) and tgt (M, 3) float64 in the
    caller's units, and what each stage found (None where it did not run)."""

    src: np.ndarray
    tgt: np.ndarray
    features: FeatureEstimate | None = None
    sampled: Normalised | None = None
    estimate: PairEstimate | None = None


class Landing(NamedTuple):
    """Where a motion lays the source on the target (the :class:`~dit_jax.pipeline.result.Result` fields of the same
    names): ``source_indices`` (n,), the rows of the source it was measured on; ``correspondences`` (n,), the
    target row each was matched to; ``confidence`` (n,) in [0, 1]; ``inlier_ratio``; ``fitness``."""

    source_indices: np.ndarray
    correspondences: np.ndarray
    confidence: np.ndarray
    inlier_ratio: float
    fitness: float


def register_pairs(
    params,
    config: DITConfig,
    settings: InferenceSettings,
    pairs: Sequence[tuple],
    *,
    batch_size: int = 8,
    on_pair: Callable[[int], None] | None = None,
) -> list[Result]:
    """Registers each ``(src (N, 3), tgt (M, 3))`` of ``pairs``, in the caller's units, through the stages.
    ``config`` is the network as it runs, the settings' model overrides already applied
    (:attr:`dit_jax.pipeline.registration.Registrar.config`).

    Pairs whose sampled clouds have the same sizes go through the network together, ``batch_size`` at a time.
    ``on_pair(count)`` is called as pairs finish (a progress bar's ``update``). Raises
    :class:`~dit_jax.pipeline.sampling.InputError` on the first cloud DIT cannot register, before any other work.
    """
    checked = []
    for src, tgt in pairs:  # a loop, not a comprehension: the size warning names the caller's line
        checked.append(Pair(*check_pair(src, tgt, config.min_points)))
    found = by_features(checked, settings)
    prepared = sampled(found, settings)
    estimates = estimated(params, config, settings, prepared, batch_size)
    results = []
    for pair in estimates:
        results.append(
            features_result(pair, settings, config)
            if pair.features is not None
            else network_result(pair.sampled, pair.estimate, settings, config)
        )
        if on_pair is not None:
            on_pair(1)
    return results


class ScanSet(NamedTuple):
    """Scans registered in many pairs among themselves (:func:`prepare_scans`): the checked ``clouds`` (K of
    (N_k, 3) float64); where the settings register them by local features, their features
    (:class:`dit_jax.features.keypoints.Scans`, scan k at row ``feature_rows[k]``; -1: none for it); and each
    one's point ``spacings`` (:func:`dit_jax.geometry.neighbours.point_spacing`)."""

    clouds: list
    features: object | None
    feature_rows: list
    spacings: list


def prepare_scans(config: DITConfig, settings: InferenceSettings, clouds: Sequence) -> ScanSet:
    """K ``clouds`` checked, and the features of those the settings register by local features first
    (:func:`dit_jax.features.keypoints.prepare_scans`: each scan's once, at the set's own spacing and voxel), for
    :func:`register_scan_pairs`. Raises :class:`~dit_jax.pipeline.sampling.InputError` naming a cloud DIT cannot use."""
    from dit_jax.geometry import neighbours

    checked = [check_cloud(f"scan {k}", cloud, config.min_points) for k, cloud in enumerate(clouds)]
    spacings = [neighbours.point_spacing(cloud, seed=settings.seed) for cloud in checked]
    by_features = [
        k for k, cloud in enumerate(checked)
        if settings.refinement_for(len(cloud), len(cloud)) != "none"
        and settings.runs_feature_candidate(len(cloud), len(cloud))
    ]  # fmt: skip
    rows, features = [-1] * len(checked), None
    if len(by_features) >= 2:
        from dit_jax.features import keypoints

        viewpoint = keypoints.VIEWPOINT if settings.viewpoint == "origin" else None
        features = keypoints.prepare_scans(
            [checked[k] for k in by_features],
            seed=settings.seed,
            viewpoint=viewpoint,
            spacings=[spacings[k] for k in by_features],
            descriptor=settings.descriptor,
        )
        for row, k in enumerate(by_features):
            rows[k] = row
    return ScanSet(checked, features, rows, spacings)


def register_scan_pairs(
    params,
    config: DITConfig,
    settings: InferenceSettings,
    scans: ScanSet,
    pairs: Sequence[tuple[int, int]],
    *,
    batch_size: int = 8,
    on_pair: Callable[[int], None] | None = None,
) -> list[Result]:
    """:func:`register_pairs` for pairs ``(source, target)`` of scan indices into ``scans``
    (:func:`prepare_scans`): a pair of scans with features registers from them (as many pairs as a scene has
    make the features the larger cost, so each scan's are computed once); the other pairs, and those whose
    features find too little, go through :func:`register_pairs`."""
    from dit_jax.features import matching

    clouds, rows = scans.clouds, scans.feature_rows
    found = {}
    for s, t in pairs:
        if rows[s] >= 0 and rows[t] >= 0:
            found[(s, t)] = matching.register_scans(scans.features, rows[s], rows[t], seed=settings.seed)
            if found[(s, t)] is not None and on_pair is not None:
                on_pair(1)
    rest = [(s, t) for s, t in pairs if found.get((s, t)) is None]
    others = {}
    if rest:
        rest_pairs = [(clouds[s], clouds[t]) for s, t in rest]
        others = dict(
            zip(rest, register_pairs(params, config, settings, rest_pairs, batch_size=batch_size, on_pair=on_pair))
        )
    return [
        others[(s, t)] if (s, t) in others
        else features_result(Pair(clouds[s], clouds[t], features=found[(s, t)]), settings, config)
        for s, t in pairs
    ]  # fmt: skip


def by_features(pairs: list[Pair], settings: InferenceSettings) -> list[Pair]:
    """Stage 0: each pair with its :func:`features_first` estimate."""
    return [pair._replace(features=features_first(pair.src, pair.tgt, settings)) for pair in pairs]


def sampled(pairs: list[Pair], settings: InferenceSettings) -> list[Pair]:
    """Stage 1: each pair the features did not register, sampled and normalised for the network."""
    return [
        pair if pair.features is not None else pair._replace(sampled=sample_and_normalise(pair.src, pair.tgt, settings))
        for pair in pairs
    ]


def estimated(params, config: DITConfig, settings: InferenceSettings, pairs: list[Pair], batch_size: int) -> list[Pair]:
    """Stage 2: each sampled pair with the network's :class:`~dit_jax.pipeline.network_stage.PairEstimate`."""
    estimates = network_stage.estimate_pairs(params, config, settings, [pair.sampled for pair in pairs], batch_size)
    return [pair._replace(estimate=estimate) for pair, estimate in zip(pairs, estimates)]


# ------------------------------------------------------------------------------ stages 3 and 4: the network's


def network_result(p: Normalised, e: PairEstimate, settings: InferenceSettings, config: DITConfig) -> Result:
    """Stages 3 and 4 for a pair the network estimated (``e``): its refinement, where the settings refine
    clouds of its sizes, and the verdict; the result records the network's own motion as its first stage."""
    landing = Landing(
        source_indices=p.src_indices,
        correspondences=p.tgt_indices[e.evidence.correspondences],
        confidence=e.evidence.weights,
        inlier_ratio=e.evidence.inlier_ratio,
        fitness=e.evidence.fitness,
    )
    back = e.backward
    judged = verdict.judge(settings, "none", landing.fitness, e.forward.rotation, back and back.rotation)
    forward = Motion(e.forward.rotation, e.forward.translation)
    origin = Origin(e.seconds, None, 0.0, "forward", e.forward.start_turn)
    unrefined = _result(forward, landing, judged, origin, settings.verdict_rule, settings.unconfirmed_min_right)
    first = unrefined.as_stage("network")
    method = settings.refinement_for(len(p.src), len(p.tgt))
    if method == "none":
        return dataclasses.replace(unrefined, stages=(first,))
    backward = Motion(back.rotation, back.translation) if back is not None else None
    refined = refinement.refine_pair(
        p, forward, backward, best_direction=settings.best_direction, seed=settings.seed, method=method
    )
    motion = Motion(refined.rotation, refined.translation)
    landing = landing._replace(fitness=refinement.fitness(p, motion, config))
    judged = verdict.judge(settings, method, landing.fitness, refined.forward_rotation, refined.backward_rotation)
    turn = e.forward.start_turn if refined.direction == "forward" else back.start_turn
    origin = Origin(e.seconds, method, refined.seconds, refined.direction, turn)
    result = _result(motion, landing, judged, origin, settings.verdict_rule, settings.unconfirmed_min_right)
    return dataclasses.replace(result, stages=(first, result.as_stage("refined")))


class Origin(NamedTuple):
    """How a result was reached, beside its motion and evidence: the network's ``seconds`` (0 where it did not
    run), the ``refinement`` and its ``refine_seconds``, the ``direction`` kept and the rotation search's
    ``start_turn`` (:class:`~dit_jax.pipeline.result.Result`'s fields of the same names)."""

    seconds: float
    refinement: str | None
    refine_seconds: float
    direction: str
    start_turn: float


def _result(
    motion: Motion, landed: Landing, judged: verdict.Verdict, origin: Origin, verdict_rule: str, min_right: float
) -> Result:
    """The :class:`~dit_jax.pipeline.result.Result` of ``motion``, with its evidence, verdict and origin."""
    return Result(
        rotation=np.asarray(motion.rotation, np.float64),
        translation=np.asarray(motion.translation, np.float64),
        matrix=_matrix(motion),
        source_indices=landed.source_indices,
        correspondences=landed.correspondences,
        confidence=landed.confidence,
        inlier_ratio=landed.inlier_ratio,
        fitness=landed.fitness,
        seconds=origin.seconds,
        refinement=origin.refinement,
        refine_seconds=origin.refine_seconds,
        verdict=judged.trusted,
        level=verdict.level(judged.trusted, judged.band, min_right),
        verdict_rule=verdict_rule,
        threshold=judged.threshold,
        agreement=judged.agreement,
        direction=origin.direction,
        start_turn=origin.start_turn,
        agreement_band=judged.band,
    )


def _matrix(motion: Motion) -> np.ndarray:
    """(4, 4) the homogeneous transform of ``motion``."""
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = motion.rotation, motion.translation
    return matrix


# ------------------------------------------------------------------------------- stage 0: local features


def features_first(src: np.ndarray, tgt: np.ndarray, settings: InferenceSettings) -> FeatureEstimate | None:
    """Stage 0 for one pair: :func:`dit_jax.features.matching.register_both_ways` on the caller's clouds src (N, 3)
    and tgt (M, 3) where the settings register such clouds by local features first (and refine at all), else
    None; None too where the clouds have too few features."""
    if settings.refinement_for(len(src), len(tgt)) == "none":
        return None
    if not settings.runs_feature_candidate(len(src), len(tgt)):
        return None
    from dit_jax.features import keypoints, matching

    viewpoint = keypoints.VIEWPOINT if settings.viewpoint == "origin" else None
    return matching.register_both_ways(
        src, tgt, seed=settings.seed, viewpoint=viewpoint, descriptor=settings.descriptor
    )


def features_result(pair: Pair, settings: InferenceSettings, config: DITConfig) -> Result:
    """The result of a ``pair`` registered by local features (stage 0): the direction that lays more of the
    source onto the target, trusted where the two directions settle the pair (:func:`dit_jax.pipeline.verdict.judge_features`),
    else "probably wrong"."""
    found = pair.features
    motion = Motion(*found.kept)
    judged = verdict.judge_features(found, settings)
    landed = landing(pair.src, pair.tgt, motion, found.spacing, settings, config)
    origin = Origin(0.0, "icp", 0.0, found.kept_direction, 0.0)
    result = _result(motion, landed, judged, origin, "agreement", settings.unconfirmed_min_right)
    return dataclasses.replace(
        result,
        candidate="features",
        candidate_seconds=found.seconds,
        offset=found.offset,
        max_offset=settings.max_offset_features,
        rival=max(found.rival),
        max_rival=settings.max_rival_features,
        twin=max(found.twin),
        max_twin=settings.max_twin_features,
    )


def landing(
    src: np.ndarray, tgt: np.ndarray, motion: Motion, spacing: float, settings: InferenceSettings, config: DITConfig
) -> Landing:
    """Where a motion found without the network lays src (N, 3) on tgt (M, 3), on a seeded random
    ``settings.n_points`` of the source rows: each one's nearest target row, 1 as its confidence where that lies
    within :data:`CANDIDATE_OVERLAP` point ``spacing`` (else 0), the share of such rows as the inlier ratio,
    and the share within ``config.fitness_radius`` point spacings as the fitness."""
    from scipy.spatial import cKDTree

    rows = np.arange(len(src))
    if len(src) > settings.n_points:
        rows = np.sort(np.random.default_rng(settings.seed).choice(len(src), settings.n_points, replace=False))
    gaps, nearest = cKDTree(tgt).query(src[rows] @ motion.rotation.T + motion.translation)
    confidence = (gaps <= CANDIDATE_OVERLAP * spacing).astype(np.float64)
    return Landing(
        source_indices=rows,
        correspondences=nearest,
        confidence=confidence,
        inlier_ratio=float(confidence.mean()),
        fitness=float(np.mean(gaps <= config.fitness_radius * spacing)),
    )
