"""Iterative closest point: the local refinement that follows a global estimate (DIT's or a baseline's).

Plain NumPy and scipy (which JAX already depends on), in float64, so refinement needs no extra package and
runs on clouds of any size: the target's k-d tree is built once, and each iteration pairs every source point
with its nearest target point within a distance, then solves for the whole motion again from those pairs.

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
from typing import Sequence

import numpy as np

METHODS = ("point_to_point", "point_to_plane")
#: DIT's refinement (:func:`refine`; ``register(refine="icp")``, evaluate.py's ``DIT+ICP``): its stages'
#: pairing distances, in units of the unit sphere the network works in, and the method it uses where the
#: clouds share no points; chosen on validation pairs of training shapes (scripts/tune_baselines.py,
#: docs/baselines_tuning.md).
REFINE_DISTANCES = (0.1, 0.05)
REFINE_METHOD = "point_to_plane"
#: Clouds "share their points" when, after point-to-point ICP, the median distance from a source point to its
#: nearest target point is below this share of the target's point spacing (about 0.1 or less on the authors'
#: low-noise pairs, 0.8 and above on independently sampled ones; scripts/check_refinement.py).
SHARED_POINTS_GAP = 0.3
#: :func:`refine` keeps the estimate it was given where ICP would move the source points by more than this
#: share of the clouds' radius on average (None: no limit). On validation pairs, 0.5 keeps as many pairs
#: within 5 degrees as no limit and lowers the mean error on scan-like pairs; 0.3 or less loses pairs ICP
#: would have brought in (docs/refinement_check.md).
MAX_SHIFT = 0.5


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


def procrustes(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion (R (3, 3), t (3,)) minimising ``sum |R src_i + t - tgt_i|^2`` over paired rows of
    src, tgt (K, 3), in float64 (Kabsch, with the reflection removed)."""
    src_mean, tgt_mean = src.mean(axis=0), tgt.mean(axis=0)
    u, _, vt = np.linalg.svd((tgt - tgt_mean).T @ (src - src_mean))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt
    return rotation, tgt_mean - rotation @ src_mean


def estimate_normals(points: np.ndarray, k: int = 20, tree=None) -> np.ndarray:
    """Unit normals (N, 3) of points (N, 3): the least-variance direction of each point's k nearest
    neighbours (sign arbitrary; point-to-plane ICP does not need it)."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(points)
    _, idx = tree.query(points, k=min(k, len(points)))
    neighbours = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", neighbours, neighbours))
    return vectors[:, :, 0]


def _point_to_plane_step(src: np.ndarray, tgt: np.ndarray, normals: np.ndarray):
    """The small motion (R, t) minimising ``sum ((R src_i + t - tgt_i) . n_i)^2``, linearised in R; None
    where the system is singular (all normals parallel, say)."""
    a = np.concatenate([np.cross(src, normals), normals], axis=1)
    b = np.einsum("ni,ni->n", tgt - src, normals)
    ata = a.T @ a
    if np.linalg.cond(ata) > 1e12:
        return None
    x = np.linalg.solve(ata, a.T @ b)
    angle = np.linalg.norm(x[:3])
    if angle > 0:
        k = np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]]) / angle
        rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    else:
        rotation = np.eye(3)
    return rotation, x[3:]


def icp(src: np.ndarray, tgt: np.ndarray, rotation: np.ndarray | None = None,
        translation: np.ndarray | None = None, *, distances: float | Sequence[float] = 0.05,
        method: str = "point_to_point", max_iterations: int = 50, tolerance: float = 1e-7,
        max_points: int | None = 5_000, normal_neighbours: int = 20, seed: int = 0, tree=None) -> ICPResult:
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
      tree: a ``scipy.spatial.cKDTree`` of ``tgt`` to reuse (built here otherwise).

    Returns:
      :class:`ICPResult`, in float64.
    """
    from scipy.spatial import cKDTree

    if method not in METHODS:
        raise ValueError(f"unknown ICP method {method!r}; choose from {', '.join(METHODS)}")
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    translation = np.zeros(3) if translation is None else np.asarray(translation, np.float64)
    stages = [float(distances)] if np.ndim(distances) == 0 else [float(d) for d in distances]
    if max_points and len(src) > max_points:
        src = src[np.random.default_rng(seed).choice(len(src), max_points, replace=False)]
    tree = tree if tree is not None else cKDTree(tgt)
    normals = estimate_normals(tgt, normal_neighbours, tree) if method == "point_to_plane" else None
    extent = float(np.linalg.norm(np.ptp(src, axis=0))) or 1.0
    iterations = 0
    for distance in stages:
        for _ in range(max_iterations):
            moved = src @ rotation.T + translation
            gap, idx = tree.query(moved, distance_upper_bound=distance)
            paired = np.isfinite(gap)
            if paired.sum() < 3:
                break
            if method == "point_to_point":
                new_rotation, new_translation = procrustes(src[paired], tgt[idx[paired]])
            else:
                step = _point_to_plane_step(moved[paired], tgt[idx[paired]], normals[idx[paired]])
                if step is None:
                    break
                new_rotation = step[0] @ rotation
                new_translation = step[0] @ translation + step[1]
            iterations += 1
            # How far the update moves the cloud: the rotation change at the cloud's extent plus the shift.
            change = (np.linalg.norm(new_rotation - rotation) * extent
                      + np.linalg.norm(new_translation - translation))
            rotation, translation = new_rotation, new_translation
            if change <= tolerance * distance:
                break
    # The last stage's figures for the returned motion.
    gap, _ = tree.query(src @ rotation.T + translation, distance_upper_bound=stages[-1])
    paired = np.isfinite(gap)
    fitness = float(paired.mean())
    rmse = float(np.sqrt(np.mean(gap[paired] ** 2))) if paired.any() else 0.0
    return ICPResult(rotation=rotation, translation=translation, fitness=fitness, rmse=rmse,
                     iterations=iterations)


def spacing(points: np.ndarray, tree=None, max_points: int = 5_000, seed: int = 0) -> float:
    """The median distance from a point of ``points`` (N, 3) to its nearest other point (on a seeded random
    subset of ``max_points`` for large clouds)."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(points)
    if len(points) > max_points:
        points = points[np.random.default_rng(seed).choice(len(points), max_points, replace=False)]
    return float(np.median(tree.query(points, k=2)[0][:, 1]))


def _gap(src: np.ndarray, tree, rotation: np.ndarray, translation: np.ndarray, seed: int,
                quantile: float = 0.5) -> float:
    """A quantile (the median by default) of the distances from (up to 5,000 of) the moved source points to
    their nearest target point."""
    if len(src) > 5_000:
        src = src[np.random.default_rng(seed).choice(len(src), 5_000, replace=False)]
    return float(np.quantile(tree.query(src @ rotation.T + translation)[0], quantile))


def mean_shift(src: np.ndarray, rotation_a: np.ndarray, translation_a: np.ndarray, rotation_b: np.ndarray,
               translation_b: np.ndarray) -> float:
    """How far two motions place the points of src (N, 3) apart, on average (the clouds' units)."""
    return float(np.mean(np.linalg.norm(src @ (rotation_a - rotation_b).T + (translation_a - translation_b), axis=1)))


def refine(src: np.ndarray, tgt: np.ndarray, rotation: np.ndarray, translation: np.ndarray, *,
           scale: float = 1.0, seed: int = 0, max_shift: float | None = MAX_SHIFT) -> ICPResult:
    """DIT's refinement of a global estimate.

    First point-to-point ICP at :data:`REFINE_DISTANCES` (times ``scale``, the clouds' radius). Where that lays
    the clouds onto each other closer than :data:`SHARED_POINTS_GAP` point spacings (median distance from a
    source point to the target), they share their points (the authors' synthetic pairs): a last
    point-to-point stage pairs only points within four such median gaps, which leaves out the points one
    cloud has and the other lacks, and the result is exact up to noise. Otherwise (independently sampled
    clouds, as real scans are) point-to-plane ICP from the given estimate at the same distances, which slides
    the surfaces onto each other instead of snagging on their samples (docs/refinement_check.md).

    The estimate comes back unchanged (``iterations`` 0) where the refinement would move the source points
    by more than ``max_shift`` times ``scale`` on average (ICP from a start that far off slides partial views
    into each other rather than correcting them), and where the estimate already lays the closest quarter of
    the source points closer onto the target than the refinement does (ICP can slide a near-exact start off
    the points the clouds share, pulled by those one cloud lacks).

    Args: src (N, 3), tgt (M, 3), the estimate (3, 3), (3,), as :func:`icp`. Returns :class:`ICPResult`."""
    from scipy.spatial import cKDTree

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    distances = tuple(scale * d for d in REFINE_DISTANCES)
    tree = cKDTree(tgt)
    shared = SHARED_POINTS_GAP * spacing(tgt, tree, seed=seed)
    # The estimate as handed in, with its fitness and rmse: what comes back where the refinement is refused.
    kept = lambda: icp(src, tgt, rotation, translation, distances=distances[-1], max_iterations=0, tree=tree)
    point = icp(src, tgt, rotation, translation, distances=distances, seed=seed, tree=tree)
    gap = _gap(src, tree, point.rotation, point.translation, seed)
    if gap < shared:
        tight = max(4.0 * gap, 1e-9 * scale)
        last = icp(src, tgt, point.rotation, point.translation, distances=tight, seed=seed, tree=tree)
        result = dataclasses.replace(last, iterations=point.iterations + last.iterations)
    else:
        result = icp(src, tgt, rotation, translation, distances=distances, method=REFINE_METHOD, seed=seed,
                     tree=tree)
    if max_shift is not None and mean_shift(src, result.rotation, result.translation, rotation,
                                            translation) > max_shift * scale:
        return kept()
    # The closest quarter of the points decides: where the clouds share points, those lie on each other.
    closest = lambda r, t: _gap(src, tree, r, t, seed, quantile=0.25)
    if closest(rotation, translation) < closest(result.rotation, result.translation):
        return kept()
    return result
