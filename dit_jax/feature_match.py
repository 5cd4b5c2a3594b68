"""Registration by local features: the pipeline's candidate that needs no start and no training data.

Both clouds are thinned on a voxel grid; each kept point gets FPFH features (Rusu et al., "Fast Point Feature
Histograms (FPFH) for 3D Registration", ICRA 2009) from its neighbours; RANSAC draws three mutual feature matches
at a time and keeps the motion most matches agree with; point-to-plane ICP on every point refines it. Open3D
does each step (the global-registration recipe of its tutorial, which registered the most 3DMatch pairs of
the candidates measured in docs/benchmarks.md, "Candidates on rooms"). It finds a motion at any turn, so it
covers what the network never learned: rooms turned by anything, LiDAR, scans of any object.

Every length is set in the clouds' own scale, so millimetres and metres give the same motion: the voxel is
:data:`VOXEL_SPACINGS` point spacings (:func:`dit_jax.icp.point_spacing`), coarser on very large scans so that
the features see about :data:`FEATURE_POINTS` points of each cloud (:func:`feature_voxel`); normals come from
neighbours within 2 voxels, features from those within 5, RANSAC counts matches within 1.5 voxels and ICP pairs
points within 0.4 voxels (the tutorial's ratios).

:func:`register_both_ways` registers the source onto the target and the target onto the source from the same
features. Two RANSAC runs that land on one motion are the evidence the pipeline's verdict reads
(:class:`FeatureEstimate`): a wrong motion found by chance in one direction is rarely found again in the other.

RANSAC is seeded, and a run alone repeats exactly; under load it may not, since Open3D's threads draw from one
random stream in whatever order they get to it.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

#: The voxel of the features, in point spacings: Open3D's room recipe uses 5 cm on 3DMatch fragments, whose
#: point spacing is about 1.3 cm.
VOXEL_SPACINGS = 3.75
#: On larger scans the voxel grows so that a surface sampled by the larger cloud's points keeps about this
#: many voxels (a surface's count falls with the square of the voxel), and then until neither cloud occupies
#: more than this many (a LiDAR sweep, dense near the sensor, needs the second): RANSAC's time stays bounded.
FEATURE_POINTS = 10_000
#: RANSAC's largest number of draws and its confidence (it stops sooner once this sure of its best motion).
RANSAC_DRAWS = 1_000_000
RANSAC_CONFIDENCE = 0.999
#: Clouds that occupy fewer voxels than this have too few features to match: no estimate.
MIN_VOXELS = 32


@dataclasses.dataclass(frozen=True)
class FeatureMatch:
    """A feature-based estimate ``tgt ~ src @ rotation.T + translation``, in the caller's units.

    Attributes:
      rotation: (3, 3) float64; translation: (3,) float64.
      inliers: feature matches within RANSAC's distance of the motion (0: no estimate, the identity).
      voxel: the voxel the features were computed on, in the caller's units.
    """

    rotation: np.ndarray
    translation: np.ndarray
    inliers: int
    voxel: float


@dataclasses.dataclass(frozen=True)
class FeatureEstimate:
    """:func:`register_both_ways`' result for one pair, in the caller's units: each direction refined by ICP.

    Attributes:
      forward: (R (3, 3), t (3,)), source onto target.
      backward: the inverse of the target registered onto the source, as (R, t) of the source onto the target.
      disagreement: degrees between the two rotations.
      offset: distance between the two translations, in point spacings.
      overlap: (2,) the share of source points each lays within 2 point spacings of the target
        (:func:`dit_jax.icp.overlap`).
      inliers: (2,) RANSAC's feature matches of each direction (0: that direction found nothing).
      spacing: the pair's point spacing; voxel: the features' voxel (both in the caller's units).
      seconds: wall time, features to ICP.
    """

    forward: tuple[np.ndarray, np.ndarray]
    backward: tuple[np.ndarray, np.ndarray]
    disagreement: float
    offset: float
    overlap: np.ndarray
    inliers: tuple[int, int]
    spacing: float
    voxel: float
    seconds: float

    @property
    def kept(self) -> tuple[np.ndarray, np.ndarray]:
        """The direction that lays more of the source onto the target (ties: forward)."""
        return self.backward if self.overlap[1] > self.overlap[0] else self.forward

    @property
    def kept_direction(self) -> str:
        return "backward" if self.overlap[1] > self.overlap[0] else "forward"

    def agrees(self, max_degrees: float, max_spacings: float) -> bool:
        """Whether both directions found one motion: within ``max_degrees`` and ``max_spacings``."""
        return bool(self.disagreement <= max_degrees and self.offset <= max_spacings and min(self.inliers) > 0)


def feature_voxel(spacing: float, points: int, spacings: float = VOXEL_SPACINGS) -> float:
    """The voxel of the features for clouds of this point ``spacing`` (their units) and at most ``points``
    points: ``spacings`` point spacings, or the voxel that leaves about :data:`FEATURE_POINTS` of a surface
    sampled by ``points`` points, whichever is coarser."""
    return spacing * max(spacings, float(np.sqrt(points / FEATURE_POINTS)))


def occupied_voxels(points: np.ndarray, voxel: float) -> int:
    """How many cells of a grid of ``voxel`` (the points' units) the (N, 3) ``points`` occupy."""
    cells = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    extent = cells.max(axis=0) + 1
    return len(np.unique((cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]))


def _o3d():
    try:
        import open3d
    except ImportError as error:  # the wheel loads libusb, which slim Debian images lack
        raise ImportError(
            f"registration by local features needs Open3D ({error}); on Debian: apt-get install libusb-1.0-0"
        ) from None
    return open3d


def _capped_voxel(points: np.ndarray, voxel: float, most: int) -> float:
    """``voxel``, grown until ``points`` (N, 3) occupy at most about ``most`` of its cells (a surface's count
    falls with the square of the voxel; a few rounds settle clouds whose density varies)."""
    for _ in range(8):
        occupied = occupied_voxels(points, voxel)
        if occupied <= 1.1 * most:
            break
        voxel *= float(np.sqrt(occupied / most))
    return voxel


class _Cloud:
    """One cloud as Open3D holds it: every point with normals (for ICP), and the points of the features' voxel
    grid with FPFH."""

    def __init__(self, points: np.ndarray, voxel: float):
        o3d = _o3d()
        search = o3d.geometry.KDTreeSearchParamHybrid
        self.full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        self.full.estimate_normals(search(radius=2 * voxel, max_nn=30))
        self.thinned = self.full.voxel_down_sample(voxel)
        self.thinned.estimate_normals(search(radius=2 * voxel, max_nn=30))
        self.features = o3d.pipelines.registration.compute_fpfh_feature(
            self.thinned, search(radius=5 * voxel, max_nn=100)
        )


def _ransac(src: _Cloud, tgt: _Cloud, voxel: float, seed: int) -> tuple[np.ndarray, int]:
    """RANSAC on mutual feature matches: (4 x 4 motion, inlier matches)."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # "too few matches" warnings
        found = reg.registration_ransac_based_on_feature_matching(
            src.thinned,
            tgt.thinned,
            src.features,
            tgt.features,
            True,
            1.5 * voxel,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(RANSAC_DRAWS, RANSAC_CONFIDENCE),
        )
    return np.asarray(found.transformation), len(found.correspondence_set)


def _icp(src: _Cloud, tgt: _Cloud, start: np.ndarray, voxel: float) -> np.ndarray:
    """Point-to-plane ICP over every point, pairs within 0.4 voxels: the refined 4 x 4 motion."""
    reg = _o3d().pipelines.registration
    return np.asarray(
        reg.registration_icp(
            src.full, tgt.full, 0.4 * voxel, start, reg.TransformationEstimationPointToPlane()
        ).transformation
    )


def _prepare(src, tgt, spacing: float | None, seed: int, voxel_spacings: float):
    from dit_jax import icp as icp_lib

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    if spacing is None:
        spacing = max(icp_lib.point_spacing(src, seed=seed), icp_lib.point_spacing(tgt, seed=seed))
    voxel = feature_voxel(spacing, max(len(src), len(tgt)), voxel_spacings)
    enough = np.isfinite(voxel) and voxel > 0
    if enough:
        voxel = max(_capped_voxel(src, voxel, FEATURE_POINTS), _capped_voxel(tgt, voxel, FEATURE_POINTS))
    enough = enough and all(occupied_voxels(c[:: max(1, len(c) // 4096)], voxel) >= MIN_VOXELS for c in (src, tgt))
    return src, tgt, spacing, voxel, enough


def _split(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.array(motion[:3, :3], np.float64), np.array(motion[:3, 3], np.float64)


def register(
    src: np.ndarray,
    tgt: np.ndarray,
    *,
    spacing: float | None = None,
    seed: int = 0,
    voxel_spacings: float = VOXEL_SPACINGS,
) -> FeatureMatch:
    """Registers src (N, 3) onto tgt (M, 3) by FPFH + RANSAC at the voxel of :func:`feature_voxel`, without ICP.

    Args:
      src, tgt: clouds in any units.
      spacing: their point spacing (default: the larger of the two clouds', :func:`dit_jax.icp.point_spacing`).
      seed: RANSAC's draws and the spacing's subset.
      voxel_spacings: the voxel's point spacings (see :func:`feature_voxel`).

    Returns :class:`FeatureMatch`; the identity with ``inliers`` 0 where RANSAC finds no motion or a cloud
    occupies fewer than :data:`MIN_VOXELS` voxels.
    """
    src, tgt, spacing, voxel, enough = _prepare(src, tgt, spacing, seed, voxel_spacings)
    if not enough:
        return FeatureMatch(np.eye(3), np.zeros(3), 0, voxel)
    motion, inliers = _ransac(_Cloud(src, voxel), _Cloud(tgt, voxel), voxel, seed)
    if inliers == 0 or not np.all(np.isfinite(motion)):
        return FeatureMatch(np.eye(3), np.zeros(3), 0, voxel)
    return FeatureMatch(*_split(motion), inliers, voxel)


def register_both_ways(
    src: np.ndarray,
    tgt: np.ndarray,
    *,
    spacing: float | None = None,
    seed: int = 0,
    voxel_spacings: float = VOXEL_SPACINGS,
) -> FeatureEstimate | None:
    """Registers src (N, 3) onto tgt (M, 3) and tgt onto src from one set of features, each by RANSAC then
    point-to-plane ICP (module docs). Arguments as :func:`register`. Returns None where a cloud occupies fewer
    than :data:`MIN_VOXELS` voxels (too few features); a direction RANSAC finds nothing for starts ICP from
    the identity and counts 0 inliers."""
    from dit_jax import geometry
    from dit_jax import icp as icp_lib

    started = time.perf_counter()
    src, tgt, spacing, voxel, enough = _prepare(src, tgt, spacing, seed, voxel_spacings)
    if not enough:
        return None
    source, target = _Cloud(src, voxel), _Cloud(tgt, voxel)
    there, inliers_there = _ransac(source, target, voxel, seed)
    back, inliers_back = _ransac(target, source, voxel, seed)
    starts = [m if np.all(np.isfinite(m)) else np.eye(4) for m in (there, back)]
    forward = _split(_icp(source, target, starts[0], voxel))
    backward = _split(np.linalg.inv(_icp(target, source, starts[1], voxel)))
    shares = icp_lib.overlap(src, tgt, [forward, backward], 2.0 * spacing, seed=seed)
    return FeatureEstimate(
        forward=forward,
        backward=backward,
        disagreement=geometry.rotation_angle_deg(forward[0].T @ backward[0]),
        offset=float(np.linalg.norm(forward[1] - backward[1]) / spacing),
        overlap=shares,
        inliers=(inliers_there, inliers_back),
        spacing=spacing,
        voxel=voxel,
        seconds=time.perf_counter() - started,
    )
