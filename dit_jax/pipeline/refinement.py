"""Stage 3 of the pipeline (:mod:`dit_jax.pipeline.stages`): the network's estimate refined on the full clouds.

:func:`refine_pair` refines both directions of a pair by ICP (:func:`dit_jax.geometry.icp_refine.refine`) or by
small_gicp's GICP on dense scans (:func:`dit_jax.geometry.gicp.refine_gicp`), as
:meth:`~dit_jax.pipeline.settings.InferenceSettings.refinement_for` chooses, and keeps the better fitting direction where
``best_direction`` says so. :func:`fitness` measures the kept motion as the network measures its own.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import time
from typing import NamedTuple

import jax
import numpy as np

from dit_jax.geometry import gicp, icp_refine, neighbours, rigid
from dit_jax.geometry import icp as icp_lib
from dit_jax.network.configs import DITConfig
from dit_jax.pipeline.sampling import Normalised


class Motion(NamedTuple):
    """A rigid motion in the caller's units, ``tgt ~ src @ rotation.T + translation``: (3, 3), (3,)."""

    rotation: np.ndarray
    translation: np.ndarray


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
    forward: Motion,
    backward: Motion | None,
    *,
    best_direction: bool,
    seed: int,
    method: str = "icp",
) -> Refined:
    """Stage 3 for one pair: refines ``forward``, source onto target, and ``backward``, target onto source
    (None: one direction), on the full clouds by ``method``: "icp" (:func:`dit_jax.geometry.icp_refine.refine`, the two in
    threads on scans, one after the other on small clouds) or "gicp" (:func:`dit_jax.geometry.gicp.refine_gicp` at the pair's :func:`spacing`, threaded itself); with
    ``best_direction``, keeps the inverse of the backward motion where it lays the source onto the target
    better (:func:`dit_jax.geometry.icp.fits_better`)."""
    started = time.perf_counter()
    jobs = [(pair.src, pair.tgt, *forward)]
    if backward is not None:
        jobs.append((pair.tgt, pair.src, *backward))
    if method == "gicp":
        pair_spacing = spacing(pair, seed)  # GICP works at the clouds' point spacing: measured once for the pair
        refined = [gicp.refine_gicp(*job, seed=seed, spacing=pair_spacing) for job in jobs]
    elif min(len(pair.src), len(pair.tgt)) >= neighbours.PARALLEL_MIN_TARGET:
        # Scans: mostly scipy's k-d tree queries, which release the GIL, so two threads take about half the time.
        with concurrent.futures.ThreadPoolExecutor(len(jobs)) as pool:
            refined = list(pool.map(lambda job: icp_refine.refine(*job, scale=pair.scale, seed=seed), jobs))
    else:  # small clouds' steps hold the GIL (small_gicp's queries, small NumPy calls): threads only contend
        refined = [icp_refine.refine(*job, scale=pair.scale, seed=seed) for job in jobs]
    rotation, translation, direction = refined[0].rotation, refined[0].translation, "forward"
    back_rotation = None
    if backward is not None:
        back = refined[1]
        back_rotation = back.rotation
        inverse = (back.rotation.T, -back.rotation.T @ back.translation)
        if best_direction and icp_lib.fits_better(pair.src, pair.tgt, inverse, (rotation, translation)):
            (rotation, translation), direction = inverse, "backward"
    return Refined(rotation, translation, refined[0].rotation, back_rotation, direction, time.perf_counter() - started)


def spacing(pair: Normalised, seed: int) -> float:
    """The pair's point spacing: the larger of its two clouds' (:func:`dit_jax.geometry.neighbours.point_spacing`)."""
    return max(neighbours.point_spacing(pair.src, seed=seed), neighbours.point_spacing(pair.tgt, seed=seed))


def fitness(pair: Normalised, motion: Motion, config: DITConfig) -> float:
    """The fitness of a ``motion`` in the caller's units, as the model measures it
    (:func:`dit_jax.geometry.rigid.fitness` on the sampled clouds)."""
    moved = ((pair.src[pair.src_indices] @ motion.rotation.T + motion.translation) - pair.tgt_centre) / pair.scale
    return float(
        _fitness_within_spacings(
            np.asarray(moved, np.float32), np.asarray(pair.tgt_n, np.float32), np.float32(config.fitness_radius)
        )
    )


@jax.jit
def _fitness_within_spacings(moved: jax.Array, tgt: jax.Array, spacings: jax.Array) -> jax.Array:
    """:func:`dit_jax.geometry.rigid.fitness` of moved (N, 3) on tgt (M, 3) within ``spacings`` of the target's
    point spacing: one compiled program per pair of cloud sizes, where op-by-op dispatch compiles each of
    its operations."""
    return rigid.fitness(moved, tgt, spacings * rigid.spacing(tgt))
