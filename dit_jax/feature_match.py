"""Classical global registration on local features: the pipeline's second candidate.

Where the network's result is not confirmed, :func:`dit_jax.pipeline.register_pairs` also registers the pair
by KISS-Matcher (Lim et al., "KISS-Matcher: Fast and Robust Point Cloud Registration Revisited", ICRA 2025;
the ``kiss-matcher`` wheel, C++ with threads): both clouds thinned on a voxel grid, FasterPFH features,
mutual matches pruned by ROBIN's graph of pairwise-consistent matches, and the motion from a graduated
non-convexity solver. It needs no start and no training data, so it covers what the network never learned
(rooms, LiDAR), and it is fast on dense scans because everything after the voxel grid sees a few thousand
points.

Its parameters are set in the clouds' own scale (:func:`feature_voxel`): the voxel is at least
:data:`MIN_VOXEL_SPACINGS` point spacings (:func:`dit_jax.icp.point_spacing`), and coarser on large scans, so
that the features see about :data:`FEATURE_POINTS` points of each cloud. The clouds are then scaled so that
this voxel is KISS-Matcher's own default (:data:`NATIVE_VOXEL`, metres for LiDAR), which keeps the library's
absolute noise-bound clamps in the range it was made for. So millimetres and metres give the same motion.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: The finest voxel of the features, in point spacings: the finest of those tried registered the most of the
#: shared real scans (docs/refinement.md, benchmarks/feature_voxel.py).
MIN_VOXEL_SPACINGS = 2.0
#: On larger scans the voxel grows so that a surface sampled by the larger cloud's points keeps about this
#: many voxels (a surface's count falls with the square of the voxel): the time stays bounded.
FEATURE_POINTS = 10_000
#: KISS-Matcher's default voxel size (it was made for LiDAR in metres); clouds are scaled to meet it.
NATIVE_VOXEL = 0.3
#: Clouds that occupy fewer voxels than this are not handed to the library (it crashes the process on a few
#: points); their feature match is "no estimate".
MIN_VOXELS = 32


@dataclasses.dataclass(frozen=True)
class FeatureMatch:
    """A feature-based estimate ``tgt ~ src @ rotation.T + translation``, in the caller's units.

    Attributes:
      rotation: (3, 3) float64; translation: (3,) float64.
      inliers: matches the solver kept (0: no estimate; the motion is then the identity).
      voxel: the voxel the features were computed on, in the caller's units.
    """

    rotation: np.ndarray
    translation: np.ndarray
    inliers: int
    voxel: float


def feature_voxel(spacing: float, points: int, min_spacings: float = MIN_VOXEL_SPACINGS) -> float:
    """The voxel of the features for clouds of this point ``spacing`` (their units) and at most ``points``
    points: ``min_spacings`` spacings, or the voxel that leaves about :data:`FEATURE_POINTS` of a surface
    sampled by ``points`` points, whichever is coarser."""
    return spacing * max(min_spacings, float(np.sqrt(points / FEATURE_POINTS)))


def occupied_voxels(points: np.ndarray, voxel: float) -> int:
    """How many cells of a grid of ``voxel`` (the points' units) the (N, 3) ``points`` occupy."""
    cells = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    extent = cells.max(axis=0) + 1
    return len(np.unique((cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]))


def _enough_voxels(points: np.ndarray, voxel: float) -> bool:
    """Whether ``points`` occupy at least :data:`MIN_VOXELS` cells: a few thousand of them usually tell."""
    subset = points[:: max(1, len(points) // 4096)]
    return occupied_voxels(subset, voxel) >= MIN_VOXELS or occupied_voxels(points, voxel) >= MIN_VOXELS


def register(
    src: np.ndarray,
    tgt: np.ndarray,
    *,
    spacing: float | None = None,
    seed: int = 0,
    voxel_spacings: float | None = None,
) -> FeatureMatch:
    """Registers src (N, 3) onto tgt (M, 3) by KISS-Matcher at the voxel of :func:`feature_voxel`.

    Args:
      src, tgt: clouds in any units.
      spacing: their point spacing (default: the larger of the two clouds', :func:`dit_jax.icp.point_spacing`).
      seed: the spacing's subset.
      voxel_spacings: a voxel of this many point spacings instead of :func:`feature_voxel`'s.

    Returns :class:`FeatureMatch`; the identity with ``inliers`` 0 where the matcher finds no motion or the
    clouds occupy fewer than :data:`MIN_VOXELS` voxels.
    """
    import kiss_matcher

    from dit_jax import icp as icp_lib

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    if spacing is None:
        spacing = max(icp_lib.point_spacing(src, seed=seed), icp_lib.point_spacing(tgt, seed=seed))
    voxel = feature_voxel(spacing, max(len(src), len(tgt))) if voxel_spacings is None else voxel_spacings * spacing
    identity = FeatureMatch(np.eye(3), np.zeros(3), 0, voxel)
    if not np.isfinite(voxel) or voxel <= 0 or not (_enough_voxels(src, voxel) and _enough_voxels(tgt, voxel)):
        return identity
    # One centre and one factor for both clouds, so the motion maps back exactly: with x' = f (x - c),
    # y' = R x' + t' gives y = R x + t' / f + c - R c.
    centre = tgt.mean(axis=0)
    factor = NATIVE_VOXEL / voxel
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel_size=NATIVE_VOXEL))
    try:
        solution = matcher.estimate(
            ((src - centre) * factor).astype(np.float32), ((tgt - centre) * factor).astype(np.float32)
        )
    except RuntimeError:  # the library refuses some inputs (too few points after the voxel grid, say)
        return identity
    inliers = int(matcher.get_num_final_inliers()) if solution.valid else 0
    rotation = np.asarray(solution.rotation, np.float64)
    translation = np.asarray(solution.translation, np.float64).reshape(3)
    if inliers == 0 or not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(translation))):
        return identity
    return FeatureMatch(rotation, translation / factor + centre - rotation @ centre, inliers, voxel)
