"""Iterative closest point: the local refinement that follows a global estimate (DIT's or a baseline's).

Written here, in NumPy and a k-d tree (:func:`nearest_points`), float64, because DIT's refinement (:func:`refine`) is a choice
among ICP runs that the libraries do not offer: trimmed runs (the closest share of the pairs, Chetverikov et
al.), point-to-point and point-to-plane runs from one start, each stopped at a tolerance on the motion's step
and judged by a trimmed fit. small_gicp's ICP has neither trimming nor that stopping rule, Open3D's offers
robust kernels instead of trimming; both are faster per iteration, and replacing the candidates by theirs
would change the refinement that the validation chose (docs/refinement.md, "One ICP per job"). small_gicp's
GICP serves dense scans (:func:`refine_gicp`). The target's k-d tree is built once, and each iteration pairs
every source point with its nearest target point within a distance, then solves for the whole motion again
from those pairs. :func:`refine` runs its descents side by side, one query and one batched solve a step for
all of them, each run ending exactly where it would alone.

* :func:`icp` -- point-to-point (Besl and McKay 1992): each iteration is a Procrustes (Kabsch) solve.
* ``method="point_to_plane"`` (Chen and Medioni 1992): each iteration minimises the distances along the
  target's normals, linearised in the rotation; normals come from the covariance of each target point's
  neighbours (:func:`estimate_normals`). It slides along flat parts instead of snagging on their samples,
  which matters where the two clouds were sampled independently.
* ``distances`` can be a schedule, coarse to fine (0.1 then 0.05, say): the coarse stage pulls in an
  estimate several degrees off, the fine one keeps outliers and the non-overlapping parts out.

Degenerate input never gives NaN: a stage with fewer than three pairs (or a singular system) keeps the
estimate it was handed.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

METHODS = ("point_to_point", "point_to_plane")
#: DIT's refinement (:func:`refine`; ``register(refine="icp")``, evaluate.py's ``DIT+ICP``): the ICP runs it
#: tries from the estimate it is handed, as (method, pairing distances in units of the clouds' radius, trim).
#: No single run suits every pair: point-to-point pairs shared points exactly, point-to-plane slides
#: independently sampled surfaces together, and trimmed runs keep partial views from being pulled by the
#: parts one view lacks. Chosen on validation pairs of training shapes (docs/refinement_check.md).
REFINE_CANDIDATES = (
    ("point_to_point", (0.1, 0.05), None),
    ("point_to_point", (0.1, 0.05, 0.02), None),
    ("point_to_plane", (0.1, 0.05, 0.02), None),
    ("point_to_point", (0.1, 0.05, 0.02), 0.5),
    ("point_to_plane", (0.1, 0.05), 0.5),
)
#: Each stage of a :func:`refine` run stops after this many iterations, or once an update moves no point by
#: more than :data:`REFINE_TOLERANCE` times the stage's pairing distance (:func:`icp`'s ``tolerance``).
REFINE_ITERATIONS = 50
REFINE_TOLERANCE = 1e-7
#: :func:`trimmed_fit` scores a motion by its closest FIT_SHARE of the source points, so the parts of a
#: partial view the other cloud lacks do not count (validation: 0.7 beats the median and the closest half).
FIT_SHARE = 0.7
#: :func:`refine` never takes a run that moves the source points by more than this share of the clouds'
#: radius on average from the estimate it was handed (None: no limit): ICP from a start that far off slides
#: partial views into each other rather than correcting them.
MAX_SHIFT = 0.5
#: :func:`refine` also descends from the estimate moved by the ``starts`` best offsets, by :func:`trimmed_fit`
#: at the estimate's rotation, of a grid -span..span in steps of ``step`` (units of the clouds' radius) on
#: each axis: on noisy partial views ICP slides the two along each other and stops 0.2-0.3 off in
#: translation, and no start near the estimate leads back (validation: docs/refinement_check.md).
TRANSLATION_SEARCH = (0.3, 0.1, 3)
#: Source points (a seeded random subset) that score the translation grid of :func:`refine`.
GRID_POINTS = 500
#: :func:`refine` pairs its source points (at most ``max_points``, 2,000) with a seeded random subset of at
#: most this many target points: denser targets only slow the k-d tree, for the same result
#: (docs/benchmarks.md, "Dense scans").
TARGET_POINTS = 50_000

#: small_gicp's k-d tree (:func:`nearest_points`) queries in threads only batches of at least this many points.
THREADED_QUERY = 20_000
#: :func:`nearest_points` uses scipy's k-d tree on clouds of at least this many points (it stops searching at
#: the pairing distance and releases the GIL, so two directions also refine in threads,
#: :func:`dit_jax.refinement.refine_pair`); on smaller ones small_gicp's, whose query of a few hundred points
#: takes a third of the time but holds the GIL, so the two directions refine one after the other
#: (docs/refinement.md, "Small clouds' ICP").
PARALLEL_MIN_TARGET = 10_000


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


def estimate_normals(points: np.ndarray, k: int = 20, tree=None) -> np.ndarray:
    """Unit normals (N, 3) of points (N, 3): the least-variance direction of each point's k nearest
    neighbours (sign arbitrary; point-to-plane ICP does not need it)."""
    tree = tree if tree is not None else nearest_points(points)
    _, idx = tree.query(points, k=min(k, len(points)))
    neighbours = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", neighbours, neighbours))
    return vectors[:, :, 0]


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


def nearest_points(points: np.ndarray, *, workers: int | None = None):
    """The nearest of ``points`` (M, 3) to any point, as ``scipy.spatial.cKDTree.query`` answers for one
    neighbour: ``query(x, distance_upper_bound=inf)`` gives (distances, indices), inf and M where none lies
    below the bound. Below :data:`PARALLEL_MIN_TARGET` points, small_gicp's k-d tree, whose query of a few
    hundred points takes a third of scipy's; from there, scipy's, which stops searching at the bound (far
    faster on large scans). scipy's queries in ``workers`` threads (default: the machine's cores),
    small_gicp's only batches of at least :data:`THREADED_QUERY` points."""
    points = np.asarray(points, np.float64)
    workers = max(1, int(workers or os.cpu_count() or 1))
    if len(points) >= PARALLEL_MIN_TARGET:
        return _ScipyTree(points, workers)
    return _SmallTree(points, workers)


class _ScipyTree:
    """:func:`nearest_points` on a large cloud: scipy's k-d tree, queried in ``workers`` threads."""

    def __init__(self, points: np.ndarray, workers: int):
        from scipy.spatial import cKDTree

        self.tree, self.workers = cKDTree(points), workers

    def query(self, x: np.ndarray, distance_upper_bound: float = np.inf, k: int = 1):
        return self.tree.query(x, k=k, distance_upper_bound=distance_upper_bound, workers=self.workers)


class _SmallTree:
    """:func:`nearest_points` on a small cloud: small_gicp's k-d tree, large batches queried in ``workers``
    threads."""

    def __init__(self, points: np.ndarray, workers: int = 1):
        import small_gicp

        self.points, self.workers = np.ascontiguousarray(points, np.float64), workers
        self.tree = small_gicp.KdTree(self.points) if len(self.points) else None

    def query(self, x: np.ndarray, distance_upper_bound: float = np.inf, k: int = 1):
        x = np.ascontiguousarray(x, np.float64).reshape(-1, 3)
        if self.tree is None:  # nothing to find: every point's nearest is "none"
            idx, gap = np.zeros((len(x), k), np.intp), np.full((len(x), k), np.inf)
        else:
            # Threads only for large batches: on each step's few thousand points they gain a fifth alone, but
            # where another process shares the cores OpenMP's waiting threads double the time (refinement.md).
            threads = self.workers if len(x) >= THREADED_QUERY else 1
            found, squared = self.tree.batch_knn_search(x, k, threads)
            idx, gap = found.astype(np.intp), np.sqrt(squared)
        far = ~(gap < distance_upper_bound)
        gap[far], idx[far] = np.inf, len(self.points)
        return (gap[:, 0], idx[:, 0]) if k == 1 else (gap, idx)


class _Run(NamedTuple):
    """How the runs of :func:`_runs_side_by_side` run: ``method``, their stages' pairing ``distances`` (the
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
      tree: the target's nearest points to reuse (:func:`nearest_points`, or a ``scipy.spatial.cKDTree``; built
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
        src = _subset(src, max_points, seed)
    tree = tree if tree is not None else nearest_points(tgt)
    if method == "point_to_plane" and normals is None:
        normals = estimate_normals(tgt, normal_neighbours, tree if isinstance(tree, (_ScipyTree, _SmallTree)) else None)
    run = _Run(method, stages, trim)
    rotations, translations, iterations = _runs_side_by_side(
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


def _runs_side_by_side(
    src: np.ndarray,
    tgt: np.ndarray,
    tree,
    normals,
    rotation: np.ndarray,
    translation: np.ndarray,
    run: _Run,
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

    src = _thinned(np.asarray(src, np.float64), max_points, seed)
    tree = cKDTree(np.asarray(tgt, np.float64), balanced_tree=False, compact_nodes=False)  # few queries: quick to build
    shares = []
    for rotation, translation in motions:
        moved = src @ np.asarray(rotation, np.float64).T + np.asarray(translation, np.float64)
        gaps = tree.query(moved, distance_upper_bound=radius)[0]
        shares.append(float(np.mean(gaps <= radius)))
    return np.asarray(shares)


def _thinned(points: np.ndarray, most: int, seed: int = 0) -> np.ndarray:
    """``points`` (N, 3), or a seeded random ``most`` of them (in their order) where N is larger."""
    if len(points) <= most:
        return points
    return points[np.sort(np.random.default_rng(seed).choice(len(points), most, replace=False))]


def fits_better(src: np.ndarray, tgt: np.ndarray, motion: tuple, other: tuple) -> bool:
    """Whether ``motion`` (R (3, 3), t (3,)) lays src (N, 3) onto tgt (M, 3) better than ``other`` does, by
    :func:`trimmed_fit` (against a seeded random :data:`TARGET_POINTS` of a larger target: both motions
    against the same points). Against the true motion: where it does, the points themselves prefer that pose, and
    no refinement that fits them can be expected to end at the truth. Between two estimates: the one to keep
    (:class:`dit_jax.registration.Registrar`'s ``best_direction``)."""
    src = np.asarray(src, np.float64)
    tree = nearest_points(_thinned(np.asarray(tgt, np.float64), TARGET_POINTS))
    as_float = lambda m: (np.asarray(m[0], np.float64), np.asarray(m[1], np.float64))
    return trimmed_fit(src, tree, *as_float(motion)) < trimmed_fit(src, tree, *as_float(other))


#: :func:`best_start` keeps the first estimate (the unturned start's) unless another fits the clouds better
#: by this factor (its score below this share of the first's): a symmetric shape fits a turned copy of
#: itself nearly as well as the truth, and where the motion is small the unturned start is the right one.
#: Chosen on validation pairs of training shapes, three settings that share no point, turned 0-180 degrees,
#: as the value that keeps the unturned start's accuracy for small turns and gains most beyond
#: (docs/refinement.md, "Clouds at any rotation").
START_MARGIN = 0.7
#: The short ICP of :func:`start_scores`, which ranks the starts: pairing distances in units of the clouds' radius.
START_DISTANCES = (0.1, 0.05)


def start_scores(
    src: np.ndarray,
    tgt: np.ndarray,
    starts: tuple[np.ndarray, np.ndarray],
    *,
    scale: float = 1.0,
    max_points: int = 500,
    seed: int = 0,
) -> np.ndarray:
    """How well each of several estimates of one motion lays src (N, 3) onto tgt (M, 3) after a short
    point-to-point ICP from it (:data:`START_DISTANCES` times ``scale``): (K,) :func:`trimmed_fit` scores of
    where the ICP ends, lower is better, for ``starts``: rotations (K, 3, 3) and translations (K, 3).
    ``max_points``: the ICP and the score use a seeded random subset of this many source points."""
    from scipy.spatial import cKDTree

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    tree = cKDTree(tgt)
    rotations, translations = (np.asarray(a, np.float64) for a in starts)
    scores = []
    for rotation, translation in zip(rotations, translations):
        run = icp(
            src,
            tgt,
            rotation,
            translation,
            distances=tuple(scale * d for d in START_DISTANCES),
            max_points=max_points,
            seed=seed,
            tree=tree,
        )
        scores.append(trimmed_fit(src, tree, run.rotation, run.translation, seed=seed, max_points=max_points))
    return np.asarray(scores)


def best_start(scores: np.ndarray, margin: float = START_MARGIN) -> int:
    """Which estimate to go on from (``register(..., rotation_search=True)``), given their
    :func:`start_scores` (K,), the first the preferred one: the best scoring if its score is below ``margin``
    times the first's, else the first (index 0)."""
    scores = np.asarray(scores, np.float64)
    best = int(np.argmin(scores))
    return best if scores[best] < margin * scores[0] else 0


def mean_shift(
    src: np.ndarray,
    rotation_a: np.ndarray,
    translation_a: np.ndarray,
    rotation_b: np.ndarray,
    translation_b: np.ndarray,
) -> float:
    """How far two motions place the points of src (N, 3) apart, on average (the clouds' units)."""
    return float(np.mean(np.linalg.norm(src @ (rotation_a - rotation_b).T + (translation_a - translation_b), axis=1)))


def _translation_offsets(span: float, step: float) -> np.ndarray:
    """(G, 3) the offsets of a cubic grid, -span..span in steps of ``step`` on each axis, zero excluded."""
    axis = np.arange(-span, span + step / 2, step)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return grid[np.linalg.norm(grid, axis=1) > step / 2]


def refine(
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    scale: float = 1.0,
    seed: int = 0,
    max_shift: float | None = MAX_SHIFT,
    rounds: int = 2,
    max_points: int = 2_000,
    max_target_points: int | None = TARGET_POINTS,
    translation_search: tuple[float, float, int] | None = TRANSLATION_SEARCH,
    workers: int | None = None,
) -> ICPResult:
    """DIT's refinement of a global estimate: the best fit among several ICP runs and the estimate itself.

    Each round runs every :data:`REFINE_CANDIDATES` ICP from the current estimate (distances times
    ``scale``, the clouds' radius) and keeps whichever motion -- one of those runs or the current estimate
    -- has the lowest :func:`trimmed_fit`; the next round starts from it. So the estimate comes back
    unchanged (``iterations`` 0) where no run lays the clouds on each other better: an exact start on
    shared points, or a start ICP would only slide along a partial view. Runs that move the source points
    more than ``max_shift`` times ``scale`` on average from the estimate handed in are never taken.

    Then, unless the fit is already exact, the same descent runs again from a few shifted starts: the
    offsets of a translation grid (``translation_search``, see :data:`TRANSLATION_SEARCH`) that fit best at
    the estimate's rotation. The best fit of all is returned, so the result never fits worse than the plain
    descent's.

    Args: src (N, 3), tgt (M, 3), the estimate (3, 3), (3,), as :func:`icp`; ``rounds`` (at least 1) stops
    early once a round keeps its start; ``max_points``: the runs and the fit use a seeded random subset of
    this many source points, which bounds the time on large scans; ``max_target_points``: likewise for the
    target (:data:`TARGET_POINTS`; None: the whole target); ``translation_search``: (span, step, starts) in
    units of ``scale``, or None for the plain descent; ``workers``: threads for the nearest-point queries
    (:func:`nearest_points`; default: the machine's cores; any number gives the same result). The plain and the searched descents run side by side (:func:`_runs_side_by_side`).
    Returns :class:`ICPResult` (fitness and rmse at the finest candidate distance).
    """
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    start = (np.asarray(rotation, np.float64), np.asarray(translation, np.float64))
    if max_target_points:
        tgt = _thinned(tgt, max_target_points, seed)
    # The runs and the fit use one seeded subset of the source (icp's and trimmed_fit's own).
    runs_src = _subset(src, max_points, seed)
    tree = nearest_points(tgt, workers=workers)
    score = lambda r, t: trimmed_fit(runs_src, tree, r, t, seed=seed, max_points=max_points)  # noqa: E731
    starts = [start]
    if translation_search is not None:
        starts += _searched_starts(src, tree, start, scale, seed, translation_search)
    # The searched descents run beside the plain one, though they count only where its fit is not exact.
    normals = estimate_normals(tgt, tree=tree)
    descents = _descents(src, runs_src, tgt, tree, normals, score, start, starts, scale, rounds, max_shift)
    (best, best_score, iterations), searched = descents[0], descents[1:]
    # An exact fit (shared points at the true pose) cannot be bettered; the search would only cost time.
    if best_score > (1e-6 * scale) ** 2:
        for run, run_score, run_iterations in searched:  # in the grid's order
            iterations += run_iterations
            shift_ok = max_shift is None or mean_shift(src, run[0], run[1], *start) <= max_shift * scale
            if run[2] and shift_ok and run_score < best_score:
                best, best_score = run, run_score
    finest = scale * min(min(distances) for _, distances, _ in REFINE_CANDIDATES)
    final = icp(src, tgt, best[0], best[1], distances=finest, max_iterations=0, tree=tree)
    return dataclasses.replace(final, iterations=iterations if best[2] else 0)


def _subset(points: np.ndarray, most: int, seed: int) -> np.ndarray:
    """``points`` (N, 3), or the seeded random ``most`` of them that :func:`icp` and :func:`trimmed_fit` take."""
    if len(points) <= most:
        return points
    return points[np.random.default_rng(seed).choice(len(points), most, replace=False)]


def _descents(
    src, runs_src, tgt, tree, normals, score, start, starts, scale: float, rounds: int, max_shift: float | None
) -> list[tuple[tuple, float, int]]:
    """:func:`refine`'s descent from each of ``starts`` ((R, t) pairs), all side by side: up to ``rounds``
    rounds in which every :data:`REFINE_CANDIDATES` ICP in turn runs from the best motion so far and is kept
    where ``score`` (lower is better) improves and it moves src no further than ``max_shift`` times ``scale``
    from ``start``; a descent stops after a round that keeps nothing. The runs move ``runs_src``, a subset
    of src. A candidate runs once from any one motion: where it comes to a motion it ran from before (the
    next round, after another candidate improved; two descents at one motion), its run is taken as it was.
    Returns, for each start, the best motion (R, t, the iterations of the run that found it; 0: the start
    itself), its score and the iterations of the runs it ran."""

    def runs_from(candidate, motions):  # each run's R, t, iterations and score (None: it moved too far)
        method, distances, trim = candidate
        run = _Run(method, tuple(scale * d for d in distances), trim)
        found = _runs_side_by_side(
            runs_src, tgt, tree, normals, [r for r, _ in motions], [t for _, t in motions], run,
            max_iterations=REFINE_ITERATIONS, tolerance=REFINE_TOLERANCE,
        )  # fmt: skip
        for rotation, translation, run_iterations in zip(*found):
            too_far = max_shift is not None and mean_shift(src, rotation, translation, *start) > max_shift * scale
            yield rotation, translation, int(run_iterations), None if too_far else score(rotation, translation)

    best = [(r, t, 0) for r, t in starts]
    best_score = [score(r, t) for r, t in starts]
    iterations = [0] * len(starts)
    ran = {}  # (candidate, the motion's bytes) -> runs_from's record of that run
    going = list(range(len(starts)))
    for _ in range(rounds):
        improved = set()
        for candidate in REFINE_CANDIDATES:
            keys = {k: (candidate, best[k][0].tobytes(), best[k][1].tobytes()) for k in going}
            new = {}  # the motions this candidate has not run from, each with the first descent at it
            for k, key in keys.items():
                if key not in ran:
                    new.setdefault(key, k)
            ran.update(zip(new, runs_from(candidate, [best[k][:2] for k in new.values()])))
            for k in going:
                rotation, translation, run_iterations, run_score = ran[keys[k]]
                iterations[k] += run_iterations if new.get(keys[k]) == k else 0
                if run_score is not None and run_score < best_score[k]:
                    best[k], best_score[k] = (rotation, translation, run_iterations), run_score
                    improved.add(k)
        going = [k for k in going if k in improved]
        if not going:
            break
    return list(zip(best, best_score, iterations))


def _searched_starts(src, tree, start: tuple, scale: float, seed: int, search: tuple) -> list[tuple]:
    """:func:`refine`'s further starts: the estimate ``start`` moved by the ``search``'s best offsets (span,
    step, starts; :data:`TRANSLATION_SEARCH`), in the grid's order."""
    span, step, starts = search
    offsets = scale * _translation_offsets(span, step)
    # The grid is scored at the estimate's rotation, on a few hundred points (it only ranks the offsets).
    grid_scores = trimmed_fit(
        src, tree, start[0], start[1] + offsets, seed=seed, max_points=GRID_POINTS, cap=step * scale
    )
    return [(start[0], start[1] + offsets[k]) for k in np.argsort(grid_scores, kind="stable")[:starts]]


#: :func:`refine_gicp`'s resolutions, in point spacings (:func:`point_spacing`): GICP runs on voxel-thinned
#: clouds at each in turn, coarse to fine, pairing points within :data:`GICP_PAIRING` resolutions.
GICP_RESOLUTIONS = (8.0, 2.0)
GICP_PAIRING = 3.0
#: On large scans no resolution of :func:`refine_gicp` is finer than the one that leaves about this many
#: voxels of a surface sampled by the larger cloud's points (their count falls with the square of the
#: resolution): on a room fragment the fine stage at 2 spacings kept nearly every point, and took seconds.
GICP_POINTS = 10_000


def point_spacing(points: np.ndarray, *, seed: int = 0, samples: int = 2_000, tree=None) -> float:
    """The median distance from a point of ``points`` (N, 3) to its nearest other point (a seeded random
    ``samples`` of them queried against the whole cloud): the scan's own scale, in its units."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    # Built for a few thousand queries only: an unbalanced, non-compact tree builds in half the time.
    tree = tree if tree is not None else cKDTree(points, balanced_tree=False, compact_nodes=False)
    rows = np.random.default_rng(seed).choice(len(points), min(samples, len(points)), replace=False)
    return float(np.median(tree.query(points[rows], k=2)[0][:, 1]))


def refine_gicp(
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    seed: int = 0,
    threads: int | None = None,
    max_iterations: int = 30,
    spacing: float | None = None,
) -> ICPResult:
    """A fast refinement of a global estimate on the full clouds: small_gicp's generalized ICP, coarse to
    fine, at resolutions set by the clouds' point spacing (:data:`GICP_RESOLUTIONS`), so any units give the
    same motion.

    Like :func:`refine`, it never returns a motion that fits worse than the estimate it was handed: where
    GICP's :func:`trimmed_fit` is not lower than the estimate's (a start too far off, which GICP slides away
    from), the estimate comes back unchanged (``iterations`` 0).

    Args: src (N, 3), tgt (M, 3), the estimate (3, 3), (3,), ``tgt ~ src @ R.T + t``; ``seed``: the spacing's
    and the fit's subsets; ``threads``: small_gicp's (default: the machine's cores); ``spacing``: the clouds'
    point spacing where the caller knows it (default: the larger of the two, :func:`point_spacing`). The fit
    and the returned fitness are measured against a seeded random :data:`TARGET_POINTS` of a larger target.
    Returns :class:`ICPResult` (fitness and rmse at the finest pairing distance).
    """
    import small_gicp
    from scipy.spatial import cKDTree

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    target = _thinned(tgt, TARGET_POINTS, seed)
    tree = cKDTree(target, balanced_tree=False, compact_nodes=False)  # a few thousand queries: quick to build
    if spacing is None:
        spacing = max(point_spacing(src, seed=seed), point_spacing(tgt, seed=seed))
    finest_factor = max(float(np.sqrt(max(len(src), len(tgt)) / GICP_POINTS)), 1.0)
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = rotation, translation
    motion, iterations = start, 0
    if spacing > 0:
        for factor in GICP_RESOLUTIONS:
            resolution = max(factor, finest_factor) * spacing
            found = small_gicp.align(
                tgt,
                src,
                motion,
                registration_type="GICP",
                downsampling_resolution=resolution,
                max_correspondence_distance=GICP_PAIRING * resolution,
                num_threads=threads or os.cpu_count() or 1,
                max_iterations=max_iterations,
            )
            motion, iterations = np.asarray(found.T_target_source, np.float64), iterations + int(found.iterations)
    finest = GICP_PAIRING * max(GICP_RESOLUTIONS[-1], finest_factor) * spacing
    fit = lambda m: trimmed_fit(src, tree, m[:3, :3], m[:3, 3], seed=seed)  # noqa: E731
    if not np.all(np.isfinite(motion)) or fit(motion) >= fit(start):
        motion, iterations = start, 0
    final = icp(src, target, motion[:3, :3], motion[:3, 3], distances=finest, max_iterations=0, tree=tree)
    return dataclasses.replace(final, iterations=iterations)
