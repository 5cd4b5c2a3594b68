"""small_gicp's generalized ICP for dense scans (:func:`refine_gicp`), coarse to fine at resolutions set by
the clouds' point spacing, so any units give the same motion."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from dit_jax.geometry import icp, neighbours

#: :func:`refine_gicp`'s resolutions, in point spacings (:func:`~dit_jax.geometry.neighbours.point_spacing`): GICP runs on voxel-thinned
#: clouds at each in turn, coarse to fine, pairing points within :data:`GICP_PAIRING` resolutions.
GICP_RESOLUTIONS = (8.0, 2.0)


GICP_PAIRING = 3.0


#: On large scans no resolution of :func:`refine_gicp` is finer than the one that leaves about this many
#: voxels of a surface sampled by the larger cloud's points (their count falls with the square of the
#: resolution): on a room fragment the fine stage at 2 spacings kept nearly every point, and took seconds.
GICP_POINTS = 10_000


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
) -> icp.ICPResult:
    """A fast refinement of a global estimate on the full clouds: small_gicp's generalized ICP, coarse to
    fine, at resolutions set by the clouds' point spacing (:data:`GICP_RESOLUTIONS`), so any units give the
    same motion.

    Like :func:`~dit_jax.geometry.icp_refine.refine`, it never returns a motion that fits worse than the estimate it was handed: where
    GICP's :func:`~dit_jax.geometry.icp.trimmed_fit` is not lower than the estimate's (a start too far off, which GICP slides away
    from), the estimate comes back unchanged (``iterations`` 0).

    Args: src (N, 3), tgt (M, 3), the estimate (3, 3), (3,), ``tgt ~ src @ R.T + t``; ``seed``: the spacing's
    and the fit's subsets; ``threads``: small_gicp's (default: the machine's cores); ``spacing``: the clouds'
    point spacing where the caller knows it (default: the larger of the two, :func:`~dit_jax.geometry.neighbours.point_spacing`). The fit
    and the returned fitness are measured against a seeded random :data:`~dit_jax.geometry.icp.TARGET_POINTS` of a larger target.
    Returns :class:`~dit_jax.geometry.icp.ICPResult` (fitness and rmse at the finest pairing distance).
    """
    import small_gicp
    from scipy.spatial import cKDTree

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    target = icp.thinned(tgt, icp.TARGET_POINTS, seed)
    tree = cKDTree(target, balanced_tree=False, compact_nodes=False)  # a few thousand queries: quick to build
    if spacing is None:
        spacing = max(neighbours.point_spacing(src, seed=seed), neighbours.point_spacing(tgt, seed=seed))
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
    fit = lambda m: icp.trimmed_fit(src, tree, m[:3, :3], m[:3, 3], seed=seed)  # noqa: E731
    if not np.all(np.isfinite(motion)) or fit(motion) >= fit(start):
        motion, iterations = start, 0
    final = icp.icp(src, target, motion[:3, :3], motion[:3, 3], distances=finest, max_iterations=0, tree=tree)
    return dataclasses.replace(final, iterations=iterations)
