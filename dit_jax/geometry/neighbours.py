"""Nearest points on NumPy clouds: the k-d trees ICP pairs with (scipy's or small_gicp's, whichever is
faster at the size), normals from each point's neighbours, and a cloud's point spacing (its own scale)."""

from __future__ import annotations

import os

import numpy as np

#: small_gicp's k-d tree (:func:`nearest_points`) queries in threads only batches of at least this many points.
THREADED_QUERY = 20_000


#: :func:`nearest_points` uses scipy's k-d tree on clouds of at least this many points (it stops searching at
#: the pairing distance and releases the GIL, so two directions also refine in threads,
#: :func:`dit_jax.pipeline.refinement.refine_pair`); on smaller ones small_gicp's, whose query of a few hundred points
#: takes a third of the time but holds the GIL, so the two directions refine one after the other
#: (docs/refinement.md, "Small clouds' ICP").
PARALLEL_MIN_TARGET = 10_000


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
        return ScipyTree(points, workers)
    return SmallTree(points, workers)


class ScipyTree:
    """:func:`nearest_points` on a large cloud: scipy's k-d tree, queried in ``workers`` threads."""

    def __init__(self, points: np.ndarray, workers: int):
        from scipy.spatial import cKDTree

        self.tree, self.workers = cKDTree(points), workers

    def query(self, x: np.ndarray, distance_upper_bound: float = np.inf, k: int = 1):
        return self.tree.query(x, k=k, distance_upper_bound=distance_upper_bound, workers=self.workers)


class SmallTree:
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


def estimate_normals(points: np.ndarray, k: int = 20, tree=None) -> np.ndarray:
    """Unit normals (N, 3) of points (N, 3): the least-variance direction of each point's k nearest
    neighbours (sign arbitrary; point-to-plane ICP does not need it)."""
    tree = tree if tree is not None else nearest_points(points)
    _, idx = tree.query(points, k=min(k, len(points)))
    neighbours = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", neighbours, neighbours))
    return vectors[:, :, 0]


def point_spacing(points: np.ndarray, *, seed: int = 0, samples: int = 2_000, tree=None) -> float:
    """The median distance from a point of ``points`` (N, 3) to its nearest other point (a seeded random
    ``samples`` of them queried against the whole cloud): the scan's own scale, in its units."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    # Built for a few thousand queries only: an unbalanced, non-compact tree builds in half the time.
    tree = tree if tree is not None else cKDTree(points, balanced_tree=False, compact_nodes=False)
    rows = np.random.default_rng(seed).choice(len(points), min(samples, len(points)), replace=False)
    return float(np.median(tree.query(points[rows], k=2)[0][:, 1]))
