"""Stage 2 of the pipeline (:mod:`dit_jax.pipeline.stages`): the network's estimates of each pair's motion.

:func:`estimate_pairs` runs the jitted :func:`dit_jax.network.model.register` on the pairs stage 1 sampled, grouped by
their clouds' sizes and padded to a fixed batch size, so one compiled program serves every batch of a shape;
under the agreement verdict the batch runs the other way too (target onto source). With ``rotation_search``
each pair starts from the 24 turns of :data:`SEARCH_TURNS` of its source and goes on from the best fitting
(:func:`dit_jax.geometry.icp_refine.best_start`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.geometry import icp_refine, rigid
from dit_jax.network import compile_cache
from dit_jax.network.configs import DITConfig
from dit_jax.pipeline.sampling import Normalised, to_caller_units
from dit_jax.pipeline.settings import InferenceSettings

#: The turns of the source that ``rotation_search`` starts the network from: the 24 rotations of a cube, the
#: identity first (:func:`dit_jax.geometry.rigid.cube_rotations`). Every rotation lies within 62.8 degrees of one.
SEARCH_TURNS = rigid.cube_rotations()


class NetworkEstimates(NamedTuple):
    """Stage 2's output for a batch of B pairs, in the normalised frame: ``tgt_n ~ src_n @ rotation.T +
    translation``.

    Attributes:
      rotation: (B, 3, 3) float64.
      translation: (B, 3) float64.
      extras: the model's per-pair outputs (:func:`dit_jax.network.model.register`), each with a leading B axis.
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


class Evidence(NamedTuple):
    """What the network's last kept iteration says of its forward motion for one pair: the row of the sampled
    target matched to each sampled source point (``correspondences`` (n,)), each one's Procrustes weight
    (``weights`` (n,), in [0, 1]), the share GMCCE accepted (``inlier_ratio``) and the ``fitness``
    (:func:`dit_jax.network.model.register`'s extras of the same names)."""

    correspondences: np.ndarray
    weights: np.ndarray
    inlier_ratio: float
    fitness: float


@dataclasses.dataclass(frozen=True)
class PairEstimate:
    """What stage 2 found for one pair: ``forward`` (source onto target) with the network's ``evidence`` for
    it, ``backward`` (target onto source) under the agreement verdict, else None, and the network's
    ``seconds`` for both."""

    forward: Direction
    backward: Direction | None
    evidence: Evidence
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
        ``R = R' Q``, ``t = t' + R' c - R c``, and :func:`dit_jax.geometry.icp_refine.best_start` picks the one to go on from.
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
    """:func:`dit_jax.network.model.register`, its program traced once per config and shapes across processes
    (:func:`dit_jax.network.compile_cache.call`)."""

    def program(params, src, tgt):
        from dit_jax.network import model as model_lib

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
    k = icp_refine.best_start(
        icp_refine.start_scores(points, np.asarray(tgt_n, np.float64), (rotations, translations), seed=seed)
    )
    turn = round(rigid.rotation_angle_deg(SEARCH_TURNS[k]), 6)  # 0, 90, 120 or 180
    return NetworkEstimates(
        rotations[k], translations[k], jax.tree.map(lambda a: a[k], runs.extras), turn, time.perf_counter() - started
    )


def estimate_pairs(
    params, config: DITConfig, settings: InferenceSettings, sampled: Sequence[Normalised | None], batch_size: int
) -> list[PairEstimate | None]:
    """Stage 2 for a batch of pairs: the :class:`PairEstimate` of each pair stage 1 ``sampled`` (None where it
    did not: the pair was registered by local features). Pairs whose sampled clouds have the same sizes go
    through the network together, ``batch_size`` at a time; ``config`` has the settings' overrides applied."""
    groups: dict[tuple[int, int], list[int]] = {}
    for i, p in enumerate(sampled):
        if p is not None:
            groups.setdefault((len(p.src_n), len(p.tgt_n)), []).append(i)
    estimates: list[PairEstimate | None] = [None] * len(sampled)
    options = dict(rotation_search=settings.rotation_search, seed=settings.seed, batch_size=batch_size)
    for rows in groups.values():
        src_n = np.stack([sampled[i].src_n for i in rows])
        tgt_n = np.stack([sampled[i].tgt_n for i in rows])
        forward = network(params, config, src_n, tgt_n, **options)
        backward = network(params, config, tgt_n, src_n, **options) if settings.verdict_rule == "agreement" else None
        for k, i in enumerate(rows):
            estimates[i] = _pair_estimate(sampled[i], forward, backward, k)
    return estimates


def _pair_estimate(p: Normalised, forward: NetworkEstimates, backward: NetworkEstimates | None, k: int) -> PairEstimate:
    """Pair ``k`` of a batch's estimates, both directions moved back to the caller's units."""

    def direction(found: NetworkEstimates, from_centre, to_centre) -> Direction:
        translation = to_caller_units(found.rotation[k], found.translation[k], from_centre, to_centre, p.scale)
        return Direction(found.rotation[k], translation, float(found.start_turn[k]))

    seconds = float(forward.seconds[k] + (backward.seconds[k] if backward is not None else 0.0))
    return PairEstimate(
        forward=direction(forward, p.src_centre, p.tgt_centre),
        backward=direction(backward, p.tgt_centre, p.src_centre) if backward is not None else None,
        evidence=Evidence(
            correspondences=np.asarray(forward.extras["correspondences"][k]),
            weights=np.asarray(forward.extras["weights"][k], np.float64),
            inlier_ratio=float(forward.extras["inlier_ratio"][k]),
            fitness=float(forward.extras["fitness"][k]),
        ),
        seconds=seconds,
    )
