"""The registration pipeline: every registration in dit-jax runs through :func:`register_pairs`.

A batch of pairs goes through four stages, each a function of its own, after an optional first one:

0. :func:`dit_jax.feature_match.register_both_ways` (where :attr:`InferenceSettings.feature_candidate` says
   so; dense scans by default): local features register the source onto the target and the target onto the
   source; where the two agree, with no rival motion among the estimator's hypotheses and no turned twin that
   fits as well (:meth:`dit_jax.feature_match.FeatureEstimate.agrees`), the result is theirs, trusted; where
   they do not, it is their better fitting motion, "probably wrong" (:func:`features_result`). Either way
   the network does not run: on the shared room scans it registered no pair the features missed, and its
   confirmations of their motions were right less often than the features' own agreement (docs/verdict.md);

1. :func:`sample_and_normalise`: checks both clouds (:func:`check_cloud`), resamples each to the settings'
   point count by farthest-point sampling (:func:`farthest_point_sample`) and moves both into the unit
   sphere with one shared scale (:func:`normalise`; centring per :attr:`InferenceSettings.centring`);
2. :func:`network`: the jitted :func:`dit_jax.model.register` on the batch, padded to a fixed batch size so
   one compiled program serves every batch of a shape; with ``rotation_search``, from the 24 turns of
   :data:`SEARCH_TURNS` of each source, going on from the best fitting (:func:`dit_jax.icp.best_start`).
   Under the agreement verdict the batch runs the other way too (target onto source);
3. :func:`refine_pair`: ICP on the full clouds (:func:`dit_jax.icp.refine`, or small_gicp's GICP on dense
   scans, :func:`refinement_for`), both directions side by side, keeping the better fitting direction where
   :attr:`InferenceSettings.best_direction` says so;
4. :func:`judge`: the verdict, from the agreement of the two directions or from the fitness.

:meth:`dit_jax.registration.Registrar.register` is this pipeline on a batch of one; evaluate.py, the
calibration of the verdict (`tools/calibrate.py`) and the benchmarks call it on many pairs.
Every setting of the pipeline lives in one frozen :class:`InferenceSettings`, saved with the weights.

Motions map back to the caller's units (stage 2): with ``x' = (x - c_x) / s``, ``y' = (y - c_y) / s`` and
``y' = R x' + t'``, ``y = R x + s t' + c_y - R c_x``.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax import compile_cache, geometry
from dit_jax import icp as icp_lib
from dit_jax.configs import DITConfig
from dit_jax.result import VERDICT_LEVELS, Result, Stage  # noqa: F401  (importable from here as before)
from dit_jax.sampling import (  # noqa: F401
    SIZE_RATIO_WARNING,
    InputError,
    Normalised,
    SizeMismatchWarning,
    check_cloud,
    check_pair,
    farthest_point_sample,
    normalise,
    sample_and_normalise,
    to_caller_units,
)
from dit_jax.settings import (  # noqa: F401  (the pipeline's settings, importable from here as before)
    CENTRINGS,
    DENSE_POINTS,
    FAR_APART,
    FEATURE_CANDIDATES,
    MODEL_OVERRIDES,
    REFINEMENTS,
    SCAN_POINTS,
    VERDICTS,
    InferenceSettings,
    refinement_for,
)

#: The turns of the source that ``rotation_search`` starts the network from: the 24 rotations of a cube, the
#: identity first (:func:`dit_jax.geometry.cube_rotations`). Every rotation lies within 62.8 degrees of one.
SEARCH_TURNS = geometry.cube_rotations()
#: :attr:`Result.agreement_band` is quoted only from a band of at least this many validation results.
MIN_BAND_PAIRS = 10
#: A result found without the network counts a source point as landing on the target within this many
#: point spacings of a target point (its ``confidence`` and ``inlier_ratio``).
CANDIDATE_OVERLAP = 2.0


# ------------------------------------------------------------------------------------------ stage 2: network


class NetworkEstimates(NamedTuple):
    """Stage 2's output for a batch of B pairs, in the normalised frame: ``tgt_n ~ src_n @ rotation.T +
    translation``.

    Attributes:
      rotation: (B, 3, 3) float64.
      translation: (B, 3) float64.
      extras: the model's per-pair outputs (:func:`dit_jax.model.register`), each with a leading B axis.
      start_turn: (B,) degrees the rotation search turned each source before the network's run (0 without).
      seconds: (B,) each pair's share of its batch's wall time.
    """

    rotation: np.ndarray
    translation: np.ndarray
    extras: dict
    start_turn: np.ndarray
    seconds: np.ndarray


@dataclasses.dataclass(frozen=True)
class Direction:
    """One direction's network estimate for one pair, in the caller's units: ``rotation`` (3, 3),
    ``translation`` (3,) and the rotation search's ``start_turn`` (degrees)."""

    rotation: np.ndarray
    translation: np.ndarray
    start_turn: float


@dataclasses.dataclass(frozen=True)
class PairEstimate:
    """What stage 2 found for one pair: ``forward`` (source onto target) with the model's ``extras`` for it,
    ``backward`` (target onto source) under the agreement verdict, else None, and the network's ``seconds``
    for both."""

    forward: Direction
    backward: Direction | None
    extras: dict
    seconds: float


def network(
    params,
    config: DITConfig,
    src_n: np.ndarray,
    tgt_n: np.ndarray,
    *,
    rotation_search: bool = False,
    seed: int = 0,
    batch_size: int | None = None,
):
    """Stage 2: the network's estimates in the normalised frame, ``tgt_n ~ src_n @ R.T + t``.

    Args:
      params, config: the model (``config`` with the settings' overrides applied).
      src_n: (B, N, 3) float32 normalised sources; tgt_n: (B, M, 3) targets.
      rotation_search: start each pair from the 24 turns of :data:`SEARCH_TURNS` of its source, about the
        source's centroid c; an estimate (R', t') of a turned source Q x is one of the source itself,
        ``R = R' Q``, ``t = t' + R' c - R c``, and :func:`dit_jax.icp.best_start` picks the one to go on from.
      seed: the search's scoring subsets.
      batch_size: pairs per call (at most B); a short last batch is padded with repeats, so every batch runs
        one compiled program (default: B, one call). Where several batches run, the first compiles before the
        timings.

    Returns:
      :class:`NetworkEstimates` of the B pairs.
    """
    if rotation_search:
        found = [_search_one(params, config, src_n[i], tgt_n[i], seed) for i in range(len(src_n))]
        return NetworkEstimates(
            rotation=np.stack([f.rotation for f in found]),
            translation=np.stack([f.translation for f in found]),
            extras=jax.tree.map(lambda *a: np.stack(a), *[f.extras for f in found]),
            start_turn=np.asarray([f.start_turn for f in found]),
            seconds=np.asarray([f.seconds for f in found]),
        )
    return _batched(params, config, src_n, tgt_n, min(batch_size or len(src_n), len(src_n)))


def _batched(params, config: DITConfig, src_n: np.ndarray, tgt_n: np.ndarray, batch_size: int):
    outputs, seconds = [], []
    for start in range(0, len(src_n), batch_size):
        real = min(batch_size, len(src_n) - start)
        rows = np.r_[start : start + real, np.full(batch_size - real, start + real - 1)]
        src, tgt = jnp.asarray(src_n[rows]), jnp.asarray(tgt_n[rows])
        if start == 0 and len(src_n) > batch_size:  # many batches: compile outside their timings
            jax.block_until_ready(_register(params, src, tgt, config))
        started = time.perf_counter()
        out = jax.device_get(_register(params, src, tgt, config))
        seconds.append(np.full(real, (time.perf_counter() - started) / real))
        outputs.append(jax.tree.map(lambda a: a[:real], out))
    rotation, translation, extras = jax.tree.map(lambda *a: np.concatenate(a), *outputs)
    return NetworkEstimates(
        rotation=np.asarray(rotation, np.float64),
        translation=np.asarray(translation, np.float64),
        extras=extras,
        start_turn=np.zeros(len(src_n)),
        seconds=np.concatenate(seconds),
    )


def _register(params, src: jax.Array, tgt: jax.Array, config: DITConfig):
    """:func:`dit_jax.model.register`, its program traced once per config and shapes across processes
    (:func:`dit_jax.compile_cache.call`)."""

    def program(params, src, tgt):
        from dit_jax import model as model_lib  # Flax loads only where a program is traced, not read back

        return model_lib.register(params, src, tgt, config)

    return compile_cache.call("register", program, config, params, src, tgt)


def _search_one(params, config: DITConfig, src_n: np.ndarray, tgt_n: np.ndarray, seed: int) -> NetworkEstimates:
    """The rotation search for one pair: its :class:`NetworkEstimates` without the batch axis."""
    started = time.perf_counter()
    points = np.asarray(src_n, np.float64)
    centre = points.mean(axis=0)
    turned = (points - centre) @ SEARCH_TURNS.transpose(0, 2, 1) + centre
    targets = np.repeat(tgt_n[None], len(SEARCH_TURNS), axis=0)
    runs = _batched(params, config, turned.astype(np.float32), targets, len(SEARCH_TURNS))
    rotations = runs.rotation @ SEARCH_TURNS
    translations = runs.translation + runs.rotation @ centre - rotations @ centre
    k = icp_lib.best_start(
        icp_lib.start_scores(points, np.asarray(tgt_n, np.float64), (rotations, translations), seed=seed)
    )
    turn = round(geometry.rotation_angle_deg(SEARCH_TURNS[k]), 6)  # 0, 90, 120 or 180
    return NetworkEstimates(
        rotations[k], translations[k], jax.tree.map(lambda a: a[k], runs.extras), turn, time.perf_counter() - started
    )


# ------------------------------------------------------------------------------------------ stage 3: refine


@dataclasses.dataclass(frozen=True)
class Refined:
    """Stage 3's output for one pair, in the caller's units: the kept motion, the forward and backward
    refined rotations (the agreement's evidence; backward None with one direction) and which was kept."""

    rotation: np.ndarray
    translation: np.ndarray
    forward_rotation: np.ndarray
    backward_rotation: np.ndarray | None
    direction: str
    seconds: float


def refine_pair(
    pair: Normalised,
    forward: tuple,
    backward: tuple | None,
    *,
    best_direction: bool,
    seed: int,
    method: str = "icp",
    spacing: float | None = None,
) -> Refined:
    """Stage 3 for one pair: refines ``forward`` (R, t), source onto target, and ``backward``, target onto
    source (None: one direction), on the full clouds by ``method``: "icp" (:func:`dit_jax.icp.refine`, the
    two side by side) or "gicp" (:func:`dit_jax.icp.refine_gicp`, threaded itself); with
    ``best_direction``, keeps the inverse of the backward motion where it lays the source onto the target
    better (:func:`dit_jax.icp.fits_better`). ``spacing``: the clouds' point spacing for "gicp" (computed
    there otherwise)."""
    started = time.perf_counter()
    jobs = [(pair.src, pair.tgt, *forward)]
    if backward is not None:
        jobs.append((pair.tgt, pair.src, *backward))
    if method == "gicp":
        refined = [icp_lib.refine_gicp(*job, seed=seed, spacing=spacing) for job in jobs]
    else:
        # Independent NumPy and scipy work, which releases the GIL: two threads take about half the serial time.
        with concurrent.futures.ThreadPoolExecutor(len(jobs)) as pool:
            refined = list(pool.map(lambda job: icp_lib.refine(*job, scale=pair.scale, seed=seed), jobs))
    rotation, translation, direction = refined[0].rotation, refined[0].translation, "forward"
    back_rotation = None
    if backward is not None:
        back = refined[1]
        back_rotation = back.rotation
        inverse = (back.rotation.T, -back.rotation.T @ back.translation)
        if best_direction and icp_lib.fits_better(pair.src, pair.tgt, inverse, (rotation, translation)):
            (rotation, translation), direction = inverse, "backward"
    return Refined(rotation, translation, refined[0].rotation, back_rotation, direction, time.perf_counter() - started)


# ------------------------------------------------------------------------------------------ stage 4: verdict


class Verdict(NamedTuple):
    """Stage 4's judgement of one result: whether the rule ``trusted`` it, the rule's ``threshold`` (degrees
    of disagreement, or a share of fitness), the two directions' ``agreement`` (degrees; NaN under the
    fitness rule) and the validation band it falls in (:func:`agreement_band`)."""

    trusted: bool
    threshold: float
    agreement: float
    band: tuple | None


def judge(
    settings: InferenceSettings,
    refine: str,
    fitness: float,
    forward_rotation: np.ndarray,
    backward_rotation: np.ndarray | None,
) -> Verdict:
    """Stage 4: the :class:`Verdict` of one result. The agreement verdict
    trusts a result whose two directions' rotations (``forward_rotation``, source onto target, and
    ``backward_rotation``, target onto source) are within ``settings.max_disagreement(refine)`` degrees of
    inverse; the fitness verdict one whose ``fitness`` reaches ``settings.min_fitness``."""
    if settings.verdict_rule == "agreement":
        threshold = settings.max_disagreement(refine)
        agreement = geometry.rotation_angle_deg(forward_rotation @ backward_rotation)
        return Verdict(
            agreement <= threshold, threshold, agreement, agreement_band(settings.agreement_bands(refine), agreement)
        )
    return Verdict(fitness >= settings.min_fitness, settings.min_fitness, float("nan"), None)


def verdict_level(trusted: bool, band: tuple | None, min_right: float) -> str:
    """The level of :data:`VERDICT_LEVELS` of a result: "trusted" where the verdict trusts it; else
    "unconfirmed" where its agreement ``band`` (low, high, pairs, right) holds at least ``min_right`` of right
    validation results, and "probably wrong" where it holds fewer or was not measured (no band, too few
    results in it, or the fitness rule, which records none)."""
    if trusted:
        return "trusted"
    if band is not None and band[2] > 0 and band[3] / band[2] >= min_right:
        return "unconfirmed"
    return "probably wrong"


def agreement_band(bands: Sequence | None, agreement: float) -> tuple | None:
    """The (low, high, pairs, right) of ``bands`` (((upper or None, pairs, right), ...), increasing) that
    ``agreement`` (degrees) falls in; None without bands or agreement, or for a band of too few pairs."""
    if not bands or not np.isfinite(agreement):
        return None
    low = 0.0
    for high, pairs, right in bands:
        if high is None or agreement <= high:
            return (low, high, int(pairs), int(right)) if pairs >= MIN_BAND_PAIRS else None
        low = high
    return None


# ------------------------------------------------------------------------------------------ the pipeline


def register_pairs(
    params,
    config: DITConfig,
    settings: InferenceSettings,
    pairs: Sequence[tuple],
    *,
    batch_size: int = 8,
    on_pair: Callable[[int], None] | None = None,
) -> list[Result]:
    """Registers each ``(src (N, 3), tgt (M, 3))`` of ``pairs``, in the caller's units, through the four stages.
    ``config`` is the network as it runs, the settings' model overrides already applied
    (:attr:`dit_jax.registration.Registrar.config`).

    Pairs whose sampled clouds have the same sizes go through the network together, ``batch_size`` at a time.
    ``on_pair(count)`` is called as pairs finish (a progress bar's ``update``). Raises :class:`InputError` on
    the first cloud DIT cannot register, before any network work.
    """
    need = config.min_points
    clouds = []
    for src, tgt in pairs:  # a loop, not a comprehension: the size warning names the caller's line
        clouds.append(check_pair(src, tgt, need))
    features = [features_first(src, tgt, settings) for src, tgt in clouds]
    # Pairs the features registered (settled or not) do not go through the network.
    prepared = [sample_and_normalise(*pair, settings) if f is None else None for pair, f in zip(clouds, features)]
    both_ways = settings.verdict_rule == "agreement"
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(prepared):
        if p is not None:
            groups.setdefault((len(p.src_n), len(p.tgt_n)), []).append(i)
    estimates: list[PairEstimate | None] = [None] * len(prepared)
    for rows in groups.values():
        src_n = np.stack([prepared[i].src_n for i in rows])
        tgt_n = np.stack([prepared[i].tgt_n for i in rows])
        options = dict(rotation_search=settings.rotation_search, seed=settings.seed, batch_size=batch_size)
        forward = network(params, config, src_n, tgt_n, **options)
        backward = network(params, config, tgt_n, src_n, **options) if both_ways else None
        for k, i in enumerate(rows):
            estimates[i] = _pair_estimate(prepared[i], forward, backward, k)
    results = []
    for (src, tgt), p, e, found in zip(clouds, prepared, estimates, features):
        if found is not None:
            trusted = _features_agree(found, settings)
            results.append(features_result(src, tgt, found, settings, config, trusted=trusted))
        else:
            results.append(_finish(p, e, settings, config))
        if on_pair is not None:
            on_pair(1)
    return results


def _pair_estimate(p: Normalised, forward: NetworkEstimates, backward: NetworkEstimates | None, k: int) -> PairEstimate:
    """Pair ``k`` of a batch's estimates, both directions moved back to the caller's units."""

    def direction(found: NetworkEstimates, from_centre, to_centre) -> Direction:
        translation = to_caller_units(found.rotation[k], found.translation[k], from_centre, to_centre, p.scale)
        return Direction(found.rotation[k], translation, float(found.start_turn[k]))

    seconds = float(forward.seconds[k] + (backward.seconds[k] if backward is not None else 0.0))
    return PairEstimate(
        forward=direction(forward, p.src_centre, p.tgt_centre),
        backward=direction(backward, p.tgt_centre, p.src_centre) if backward is not None else None,
        extras={name: v[k] for name, v in forward.extras.items()},
        seconds=seconds,
    )


def _finish(p: Normalised, e: PairEstimate, settings: InferenceSettings, config: DITConfig) -> Result:
    """Stages 3 and 4 for one pair from its network estimates ``e`` (see :func:`register_pairs`)."""
    extras = e.extras
    common = _network_fields(p, e, settings)
    back = e.backward
    judged = judge(settings, "none", float(extras["fitness"]), e.forward.rotation, back and back.rotation)
    network_result = _result(
        e.forward.rotation,
        e.forward.translation,
        fitness=float(extras["fitness"]),
        refinement=None,
        refine_seconds=0.0,
        verdict=judged.trusted,
        threshold=judged.threshold,
        agreement=judged.agreement,
        direction="forward",
        start_turn=e.forward.start_turn,
        agreement_band=judged.band,
        **common,
    )
    network_stage = network_result.as_stage("network")
    method = settings.refinement_for(len(p.src), len(p.tgt))
    if method == "none":
        return dataclasses.replace(network_result, stages=(network_stage,))
    backward = (back.rotation, back.translation) if back is not None else None
    # GICP works at the clouds' point spacing: measured once for the pair.
    spacing = _spacing(p, settings.seed) if method == "gicp" else None
    refined = refine_pair(
        p,
        (e.forward.rotation, e.forward.translation),
        backward,
        best_direction=settings.best_direction,
        seed=settings.seed,
        method=method,
        spacing=spacing,
    )
    fitness = _fitness(p, refined.rotation, refined.translation, config)
    judged = judge(settings, method, fitness, refined.forward_rotation, refined.backward_rotation)
    turn = e.forward.start_turn if refined.direction == "forward" else back.start_turn
    result = _result(
        refined.rotation,
        refined.translation,
        fitness=fitness,
        refinement=method,
        refine_seconds=refined.seconds,
        verdict=judged.trusted,
        threshold=judged.threshold,
        agreement=judged.agreement,
        direction=refined.direction,
        start_turn=turn,
        agreement_band=judged.band,
        **common,
    )
    return dataclasses.replace(result, stages=(network_stage, result.as_stage("refined")))


def _network_fields(p: Normalised, e: PairEstimate, settings: InferenceSettings) -> dict:
    """The fields of a :class:`Result` that come from the network's run, whatever refines its motion."""
    return dict(
        source_indices=p.src_indices,
        correspondences=p.tgt_indices[np.asarray(e.extras["correspondences"])],
        confidence=np.asarray(e.extras["weights"], np.float64),
        inlier_ratio=float(e.extras["inlier_ratio"]),
        seconds=e.seconds,
        verdict_rule=settings.verdict_rule,
        min_right=settings.unconfirmed_min_right,
    )


def _spacing(p: Normalised, seed: int) -> float:
    """The pair's point spacing: the larger of its two clouds' (:func:`dit_jax.icp.point_spacing`)."""
    return max(icp_lib.point_spacing(p.src, seed=seed), icp_lib.point_spacing(p.tgt, seed=seed))


def _fitness(p: Normalised, rotation: np.ndarray, translation: np.ndarray, config: DITConfig) -> float:
    """The fitness of a motion in the caller's units, as the model measures it (:func:`dit_jax.geometry.fitness`
    on the sampled clouds)."""
    moved = ((p.src[p.src_indices] @ rotation.T + translation) - p.tgt_centre) / p.scale
    return float(
        _fitness_within_spacings(
            np.asarray(moved, np.float32), np.asarray(p.tgt_n, np.float32), np.float32(config.fitness_radius)
        )
    )


@jax.jit
def _fitness_within_spacings(moved: jax.Array, tgt: jax.Array, spacings: jax.Array) -> jax.Array:
    """:func:`dit_jax.geometry.fitness` of moved (N, 3) on tgt (M, 3) within ``spacings`` of the target's
    point spacing: one compiled program per pair of cloud sizes, where op-by-op dispatch compiles each of
    its operations."""
    return geometry.fitness(moved, tgt, spacings * geometry.spacing(tgt))


# ------------------------------------------------------------------------------- stage 0: local features


def features_first(src: np.ndarray, tgt: np.ndarray, settings: InferenceSettings):
    """Stage 0 for one pair: :func:`dit_jax.feature_match.register_both_ways` on the caller's clouds src (N, 3)
    and tgt (M, 3) where the settings register such clouds by local features first (and refine at all), else
    None; None too where the clouds have too few features."""
    if settings.refinement_for(len(src), len(tgt)) == "none":
        return None
    if not settings.runs_feature_candidate(len(src), len(tgt)):
        return None
    from dit_jax import feature_match

    viewpoint = feature_match.VIEWPOINT if settings.viewpoint == "origin" else None
    return feature_match.register_both_ways(src, tgt, seed=settings.seed, viewpoint=viewpoint)


def _features_agree(found, settings: InferenceSettings) -> bool:
    return found.agrees(
        settings.max_disagreement_features,
        settings.max_offset_features,
        settings.max_rival_features,
        settings.max_twin_features,
    )


def _landing(
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    spacing: float,
    settings: InferenceSettings,
    config: DITConfig,
) -> dict:
    """Where a motion found without the network lays src (N, 3) on tgt (M, 3), on a seeded random
    ``settings.n_points`` of the source rows: each one's nearest target row, 1 as its confidence where that lies
    within :data:`CANDIDATE_OVERLAP` point ``spacing`` (else 0), the share of such rows as the inlier ratio,
    and the share within ``config.fitness_radius`` point spacings as the fitness."""
    from scipy.spatial import cKDTree

    rows = np.arange(len(src))
    if len(src) > settings.n_points:
        rows = np.sort(np.random.default_rng(settings.seed).choice(len(src), settings.n_points, replace=False))
    gaps, nearest = cKDTree(tgt).query(src[rows] @ rotation.T + translation)
    confidence = (gaps <= CANDIDATE_OVERLAP * spacing).astype(np.float64)
    return dict(
        source_indices=rows,
        correspondences=nearest,
        confidence=confidence,
        inlier_ratio=float(confidence.mean()),
        fitness=float(np.mean(gaps <= config.fitness_radius * spacing)),
    )


def features_result(
    src: np.ndarray, tgt: np.ndarray, found, settings: InferenceSettings, config: DITConfig, *, trusted: bool
) -> Result:
    """The result of a pair of clouds src (N, 3), tgt (M, 3) registered by local features (stage 0): the
    direction that lays more of the source onto the target, ``trusted`` where the two directions settled the
    pair (:func:`_features_agree`), else "probably wrong"."""
    rotation, translation = found.kept
    return _result(
        rotation,
        translation,
        seconds=0.0,
        refinement="icp",
        refine_seconds=0.0,
        verdict=trusted,
        verdict_rule="agreement",
        threshold=settings.max_disagreement_features,
        agreement=found.disagreement,
        offset=found.offset,
        max_offset=settings.max_offset_features,
        direction=found.kept_direction,
        start_turn=0.0,
        agreement_band=None,
        candidate="features",
        candidate_seconds=found.seconds,
        rival=max(found.rival),
        max_rival=settings.max_rival_features,
        twin=max(found.twin),
        max_twin=settings.max_twin_features,
        min_right=settings.unconfirmed_min_right,
        **_landing(src, tgt, rotation, translation, found.spacing, settings, config),
    )


def _result(rotation, translation, *, min_right: float, **fields) -> Result:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    verdict = bool(fields.pop("verdict"))
    return Result(
        rotation=np.asarray(rotation, np.float64),
        translation=np.asarray(translation, np.float64),
        matrix=matrix,
        verdict=verdict,
        level=verdict_level(verdict, fields["agreement_band"], min_right),
        **fields,
    )
