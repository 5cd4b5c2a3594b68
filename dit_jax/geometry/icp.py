"""Iterative closest point: the local refinement that follows a global estimate (DIT's or a baseline's).

Written here, in NumPy and a k-d tree (:func:`~dit_jax.geometry.neighbours.nearest_points`), float64, because DIT's refinement (:func:`~dit_jax.geometry.icp_refine.refine`) is a choice
among ICP runs that the libraries do not offer: trimmed runs (the closest share of the pairs, Chetverikov et
al.), point-to-point and point-to-plane runs from one start, each stopped at a tolerance on the motion's step
and judged by a trimmed fit. small_gicp's ICP has neither trimming nor that stopping rule, Open3D's offers
robust kernels instead of trimming; both are faster per iteration, and replacing the candidates by theirs
would change the refinement that the validation chose (docs/refinement.md, "One ICP per job"). small_gicp's
GICP serves dense scans (:func:`~dit_jax.geometry.gicp.refine_gicp`). The target's k-d tree is built once, and each iteration pairs
every source point with its nearest target point within a distance, then solves for the whole motion again
from those pairs. :func:`~dit_jax.geometry.icp_refine.refine` runs its descents side by side, one query and one batched solve a step for
all of them, each run ending exactly where it would alone.

* :func:`icp` -- point-to-point (Besl and McKay 1992): each iteration is a Procrustes (Kabsch) solve.
* ``method="point_to_plane"`` (Chen and Medioni 1992): each iteration minimises the distances along the
  target's normals, linearised in the rotation; normals come from the covariance of each target point's
  neighbours (:func:`~dit_jax.geometry.neighbours.estimate_normals`). It slides along flat parts instead of snagging on their samples,
  which matters where the two clouds were sampled independently.
* ``distances`` can be a schedule, coarse to fine (0.1 then 0.05, say): the coarse stage pulls in an
  estimate several degrees off, the fine one keeps outliers and the non-overlapping parts out.

Degenerate input never gives NaN: a stage with fewer than three pairs (or a singular system) keeps the
estimate it was handed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from dit_jax.geometry import neighbours

METHODS = ("point_to_point", "point_to_plane")


#: :func:`trimmed_fit` scores a motion by its closest FIT_SHARE of the source points, so the parts of a
#: partial view the other cloud lacks do not count (validation: 0.7 beats the median and the closest half).
FIT_SHARE = 0.7


#: :func:`~dit_jax.geometry.icp_refine.refine` pairs its source points (at most ``max_points``, 2,000) with a seeded random subset of at
#: most this many target points: denser targets only slow the k-d tree, for the same result
#: (docs/benchmarks.md, "Dense scans").
TARGET_POINTS = 50_000


@dataclasses.dataclass(frozen=True)
class ICPResult:
    """A refined motion, ``tgt ~ src @ rotation.T + translation``.

    Attributes:
      rotation: (3, 3) float64.
      translation: (3,) float64.
      fitness: share of source points with a target point within the last stage's distance.
      rmse: root mean square distance of those pairs.
      iterations: iterations run over all stages.
    """

    rotation: np.ndarray
    translation: np.ndarray
    fitness: float
    rmse: float
    iterations: int


def procrustes(src: np.ndarray, tgt: np.ndarray, paired: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion (R (..., 3, 3), t (..., 3)) minimising ``sum |R src_i + t - tgt_i|^2`` over paired rows of
    src, tgt (..., K, 3), for every leading index at once, in float64 (Kabsch, with the reflection removed).
    ``paired`` (..., K) bool: only those rows count (default: all)."""
    src, tgt = np.asarray(src, np.float64), np.asarray(tgt, np.float64)
    if paired is None:
        src_mean, tgt_mean = src.mean(axis=-2), tgt.mean(axis=-2)
        weight = 1.0
    else:  # sums as products with the 0/1 weights: a tenth of the time of NumPy's sums over the points' axis
        weights = paired.astype(np.float64)[..., None, :]
        count = weights.sum(axis=-1)
        src_mean, tgt_mean = (weights @ src)[..., 0, :] / count, (weights @ tgt)[..., 0, :] / count
        weight = np.swapaxes(weights, -1, -2)
    cross = np.swapaxes((tgt - tgt_mean[..., None, :]) * weight, -1, -2) @ (src - src_mean[..., None, :])
    u, _, vt = np.linalg.svd(cross)
    flip = np.ones(u.shape[:-1])
    flip[..., 2] = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
    rotation = (u * flip[..., None, :]) @ vt
    return rotation, tgt_mean - np.einsum("...ij,...j->...i", rotation, src_mean)


def linear_quantile(values: np.ndarray, share: float) -> float:
    """``np.quantile(values, share)`` (linear interpolation) of values (K,), K >= 1, by a partial sort: the
    same number, for a tenth of the time on a few hundred values."""
    position = share * (len(values) - 1)
    below = int(np.floor(position))
    above = min(below + 1, len(values) - 1)
    part = np.partition(values, (below, above))
    low, high, fraction = part[below], part[above], position - below
    # NumPy's own interpolation, from whichever end is nearer.
    return float(high - (high - low) * (1 - fraction) if fraction >= 0.5 else low + (high - low) * fraction)


def _point_to_plane_steps(src: np.ndarray, tgt: np.ndarray, normals: np.ndarray, paired: np.ndarray):
    """For each of K runs, the small motion (R, t) minimising ``sum ((R src_i + t - tgt_i) . n_i)^2`` over its
    ``paired`` rows, linearised in R: src, tgt, normals (K, N, 3), paired (K, N) bool. Returns rotations
    (K, 3, 3), translations (K, 3) and which systems are singular (K,) bool (all normals parallel, say: their
    rows are the identity and zero)."""
    (sx, sy, sz), (nx, ny, nz) = np.moveaxis(src, -1, 0), np.moveaxis(normals, -1, 0)
    a = np.empty(src.shape[:-1] + (6,))  # each row (src x n, n): written out, np.cross costs far more
    a[..., 0], a[..., 1], a[..., 2] = sy * nz - sz * ny, sz * nx - sx * nz, sx * ny - sy * nx
    a[..., 3:] = normals
    a *= paired[..., None]
    b = np.einsum("kni,kni->kn", tgt - src, normals) * paired
    ata = a.transpose(0, 2, 1) @ a
    singular = ~(np.linalg.cond(ata) <= 1e12)  # NaN counts as singular
    x = np.zeros((len(src), 6))
    if not singular.all():
        atb = (a[~singular].transpose(0, 2, 1) @ b[~singular][..., None])[..., 0]
        x[~singular] = np.linalg.solve(ata[~singular], atb[..., None])[..., 0]
    return _axis_angle_matrices(x[:, :3]), x[:, 3:], singular


def _axis_angle_matrices(vectors: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations by the angles ``|v|`` about the axes ``v`` of vectors (K, 3) (Rodrigues)."""
    angle = np.linalg.norm(vectors, axis=1)
    axis = vectors / np.where(angle > 0, angle, 1.0)[:, None]
    k = np.zeros((len(vectors), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - k.transpose(0, 2, 1)
    return np.eye(3) + np.sin(angle)[:, None, None] * k + (1 - np.cos(angle))[:, None, None] * (k @ k)


class Run(NamedTuple):
    """How the runs of :func:`~dit_jax.geometry.icp.runs_side_by_side` run: ``method``, their stages' pairing ``distances`` (the
    clouds' units) and ``trim``, as :func:`icp` takes them."""

    method: str
    distances: tuple[float, ...]
    trim: float | None


def icp(
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray | None = None,
    translation: np.ndarray | None = None,
    *,
    distances: float | Sequence[float] = 0.05,
    method: str = "point_to_point",
    max_iterations: int = 50,
    tolerance: float = 1e-7,
    max_points: int | None = 5_000,
    normal_neighbours: int = 20,
    seed: int = 0,
    tree=None,
    trim: float | None = None,
    normals: np.ndarray | None = None,
) -> ICPResult:
    """Refines the motion moving ``src`` onto ``tgt``, starting from ``(rotation, translation)``.

    Args:
      src: (N, 3) the cloud to move.
      tgt: (M, 3) the cloud it should land on.
      rotation, translation: (3, 3), (3,) the starting estimate (default: the identity).
      distances: the largest pairing distance, in the clouds' units; a sequence runs one stage per value.
      method: "point_to_point" or "point_to_plane".
      max_iterations: per stage.
      tolerance: a stage ends when the motion's update moves no point by more than this times ``distance``.
      max_points: the source is thinned at random (seeded) to this many points; the target is used whole.
      normal_neighbours: neighbours per target normal (point-to-plane only).
      tree: the target's nearest points to reuse (:func:`~dit_jax.geometry.neighbours.nearest_points`, or a ``scipy.spatial.cKDTree``; built
        here otherwise).
      trim: keep only this share of the pairs, the closest (trimmed ICP, Chetverikov et al. 2002), so the
        points one cloud has and the other lacks pull less; None keeps every pair within the distance.
      normals: (M, 3) the target's normals to reuse (point-to-plane; estimated here otherwise).

    Returns:
      :class:`ICPResult`, in float64.
    """
    if method not in METHODS:
        raise ValueError(f"unknown ICP method {method!r}; choose from {', '.join(METHODS)}")
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    translation = np.zeros(3) if translation is None else np.asarray(translation, np.float64)
    stages = (float(distances),) if np.ndim(distances) == 0 else tuple(float(d) for d in distances)
    if max_points:
        src = subset(src, max_points, seed)
    tree = tree if tree is not None else neighbours.nearest_points(tgt)
    if method == "point_to_plane" and normals is None:
        normals = neighbours.estimate_normals(
            tgt, normal_neighbours, tree if isinstance(tree, (neighbours.ScipyTree, neighbours.SmallTree)) else None
        )
    run = Run(method, stages, trim)
    rotations, translations, iterations = runs_side_by_side(
        src,
        tgt,
        tree,
        normals,
        rotation[None],
        translation[None],
        run,
        max_iterations=max_iterations,
        tolerance=tolerance,
    )
    return _result(src, tree, rotations[0], translations[0], stages[-1], int(iterations[0]))


def runs_side_by_side(
    src: np.ndarray,
    tgt: np.ndarray,
    tree,
    normals,
    rotation: np.ndarray,
    translation: np.ndarray,
    run: Run,
    *,
    max_iterations: int,
    tolerance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K runs of one ICP (``run``'s method, stages and trim) of one (already thinned) src
    (N, 3) onto tgt (M, 3), from K starts, rotation (K, 3, 3) and translation (K, 3), each iterating as
    :func:`icp` describes, side by side: each step pairs the points of every run still going in one query of
    ``tree`` and solves their motions at once, so the Python work of a step is shared (on a few hundred points
    each run's own NumPy calls cost more than their arithmetic). ``normals``: (M, 3), for point-to-plane.
    Returns each run's rotation (K, 3, 3), translation (K, 3) and iterations (K,)."""
    rotation, translation = np.array(rotation, np.float64), np.array(translation, np.float64)
    stages = np.asarray(run.distances, np.float64)
    stage = np.zeros(len(rotation), int) if max_iterations > 0 else np.full(len(rotation), len(stages))
    steps, iterations = np.zeros(len(rotation), int), np.zeros(len(rotation), int)
    extent = float(np.linalg.norm(np.ptp(src, axis=0))) or 1.0
    while (going := np.flatnonzero(stage < len(stages))).size:
        distance = stages[stage[going]]
        moved = src @ rotation[going].transpose(0, 2, 1) + translation[going, None, :]
        gap, idx = tree.query(moved.reshape(-1, 3), distance_upper_bound=float(distance.max()))
        gap, idx = gap.reshape(len(going), -1), idx.reshape(len(going), -1)
        paired = gap < distance[:, None]  # a k-d tree's bound keeps a pair only below it
        if run.trim is not None:
            paired &= gap <= _row_quantiles(gap, paired, run.trim)[:, None]
        solved = paired.sum(axis=1) >= 3
        rows = np.flatnonzero(solved)  # the runs with pairs enough to solve
        idx, paired = np.where(paired, idx, 0)[rows], paired[rows]
        new_rotation, new_translation = rotation[going].copy(), translation[going].copy()
        if run.method == "point_to_point" and rows.size:
            new_rotation[rows], new_translation[rows] = procrustes(src, tgt[idx], paired)
        elif rows.size:
            turn, shift, singular = _point_to_plane_steps(moved[rows], tgt[idx], normals[idx], paired)
            new_rotation[rows] = turn @ rotation[going[rows]]
            new_translation[rows] = np.einsum("kij,kj->ki", turn, translation[going[rows]]) + shift
            solved[rows[singular]] = False
        # How far the update moves the cloud: the rotation change at the cloud's extent plus the shift.
        change = np.linalg.norm(new_rotation - rotation[going], axis=(1, 2)) * extent + np.linalg.norm(
            new_translation - translation[going], axis=1
        )
        moved_on = going[solved]
        rotation[moved_on], translation[moved_on] = new_rotation[solved], new_translation[solved]
        iterations[moved_on] += 1
        steps[moved_on] += 1
        # A stage ends without a solve (too few pairs, a singular system), on converging, or at its limit.
        ends = going[~solved | (change <= tolerance * distance) | (steps[going] >= max_iterations)]
        stage[ends] += 1
        steps[ends] = 0
    return rotation, translation, iterations


def _row_quantiles(values: np.ndarray, keep: np.ndarray, share: float) -> np.ndarray:
    """For each row of values (K, N), :func:`linear_quantile` of its ``keep`` (K, N) entries at ``share``,
    where at least 3 are kept (else +inf: nothing is trimmed)."""
    count = keep.sum(axis=1)
    ordered = np.sort(np.where(keep, values, np.inf), axis=1)
    position = share * (np.maximum(count, 1) - 1)
    below = np.floor(position).astype(int)
    above = np.minimum(below + 1, np.maximum(count, 1) - 1)
    low = np.take_along_axis(ordered, below[:, None], axis=1)[:, 0]
    high = np.take_along_axis(ordered, above[:, None], axis=1)[:, 0]
    fraction = position - below
    with np.errstate(invalid="ignore"):  # rows of fewer than 3 are not used
        quantile = np.where(fraction >= 0.5, high - (high - low) * (1 - fraction), low + (high - low) * fraction)
    return np.where(count >= 3, quantile, np.inf)


def _result(src: np.ndarray, tree, rotation: np.ndarray, translation: np.ndarray, distance: float, iterations: int):
    """:class:`ICPResult` of a motion, with its fitness and rmse at pairing ``distance`` (``tree``: the target's)."""
    gap, _ = tree.query(src @ rotation.T + translation, distance_upper_bound=distance)
    paired = np.isfinite(gap)
    rmse = float(np.sqrt(np.mean(gap[paired] ** 2))) if paired.any() else 0.0
    return ICPResult(rotation, translation, float(paired.mean()), rmse, iterations)


def trimmed_fit(
    src: np.ndarray,
    tree,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    share: float = FIT_SHARE,
    seed: int = 0,
    max_points: int = 5_000,
    cap: float | None = None,
) -> float | np.ndarray:
    """How well a motion lays src (N, 3) onto the target of ``tree`` (a ``cKDTree``): the mean squared
    distance from the moved source points to their nearest target points, over the closest ``share`` of
    them (a seeded random ``max_points`` of the source for large clouds). Lower is better.

    ``translation`` (G, 3) scores G motions that share ``rotation`` at once: (G,) scores. ``cap``: distances
    beyond it count as ``cap`` (the k-d tree then stops searching there, much faster for points far off).
    """
    if len(src) > max_points:
        src = src[np.random.default_rng(seed).choice(len(src), max_points, replace=False)]
    translation = np.asarray(translation, np.float64)
    moved = (src @ rotation.T)[None] + np.reshape(translation, (-1, 1, 3))
    bound = np.inf if cap is None else cap
    gaps = np.minimum(tree.query(moved.reshape(-1, 3), distance_upper_bound=bound)[0], bound)
    gaps = np.sort(gaps.reshape(len(moved), -1), axis=1)[:, : max(1, int(share * len(src)))]
    scores = np.mean(gaps**2, axis=1)
    return scores if translation.ndim == 2 else float(scores[0])


def overlap(
    src: np.ndarray, tgt: np.ndarray, motions: Sequence[tuple], radius: float, *, seed: int = 0, max_points: int = 5_000
) -> np.ndarray:
    """How much of src (N, 3) each motion lays onto tgt (M, 3): the share of the source points (a seeded
    random ``max_points`` of them) within ``radius`` of a target point, for each (R (3, 3), t (3,)) of
    ``motions``. Returns (len(motions),) in [0, 1]; higher is better.

    Unlike :func:`trimmed_fit`, which averages the closest share of the gaps whatever they are, it counts
    only points that land on the surface: between poses of views that overlap by less than that share, a
    wrong pose that piles the source into the target's middle can have the smaller trimmed gaps, but it
    lays far fewer points exactly onto it (measured on the dragon's scans 48 degrees apart).
    """
    from scipy.spatial import cKDTree

    src = thinned(np.asarray(src, np.float64), max_points, seed)
    tree = cKDTree(np.asarray(tgt, np.float64), balanced_tree=False, compact_nodes=False)  # few queries: quick to build
    shares = []
    for rotation, translation in motions:
        moved = src @ np.asarray(rotation, np.float64).T + np.asarray(translation, np.float64)
        gaps = tree.query(moved, distance_upper_bound=radius)[0]
        shares.append(float(np.mean(gaps <= radius)))
    return np.asarray(shares)


def thinned(points: np.ndarray, most: int, seed: int = 0) -> np.ndarray:
    """``points`` (N, 3), or a seeded random ``most`` of them (in their order) where N is larger."""
    if len(points) <= most:
        return points
    return points[np.sort(np.random.default_rng(seed).choice(len(points), most, replace=False))]


def subset(points: np.ndarray, most: int, seed: int) -> np.ndarray:
    """``points`` (N, 3), or the seeded random ``most`` of them that :func:`icp` and :func:`trimmed_fit` take."""
    if len(points) <= most:
        return points
    return points[np.random.default_rng(seed).choice(len(points), most, replace=False)]


def fits_better(src: np.ndarray, tgt: np.ndarray, motion: tuple, other: tuple) -> bool:
    """Whether ``motion`` (R (3, 3), t (3,)) lays src (N, 3) onto tgt (M, 3) better than ``other`` does, by
    :func:`trimmed_fit` (against a seeded random :data:`TARGET_POINTS` of a larger target: both motions
    against the same points). Against the true motion: where it does, the points themselves prefer that pose, and
    no refinement that fits them can be expected to end at the truth. Between two estimates: the one to keep
    (:class:`dit_jax.pipeline.registration.Registrar`'s ``best_direction``)."""
    src = np.asarray(src, np.float64)
    tree = neighbours.nearest_points(thinned(np.asarray(tgt, np.float64), TARGET_POINTS))
    as_float = lambda m: (np.asarray(m[0], np.float64), np.asarray(m[1], np.float64))
    return trimmed_fit(src, tree, *as_float(motion)) < trimmed_fit(src, tree, *as_float(other))
