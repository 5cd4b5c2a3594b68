"""The points local features match, in each cloud's own scale: the cloud thinned on a voxel grid of a few point
spacings (:func:`feature_voxel`), each kept point with a normal turned to face the viewpoint (a scan's sensor,
:data:`VIEWPOINT`) and a descriptor of :mod:`dit_jax.features.descriptors`; :func:`prepare_scans` readies
many scans once for all their pairs."""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import numpy as np

from dit_jax.features import descriptors
from dit_jax.features.descriptors import _o3d

#: The voxel of the features, in point spacings: Open3D's room recipe uses 5 cm on 3DMatch fragments, whose
#: point spacing is about 1.3 cm.
VOXEL_SPACINGS = 3.75


#: On larger scans the voxel grows so that a surface sampled by the larger cloud's points keeps about this
#: many voxels (a surface's count falls with the square of the voxel), and then until neither cloud occupies
#: more than this many (a LiDAR sweep, dense near the sensor, needs the second): the estimator's time stays
#: bounded.
FEATURE_POINTS = 10_000


#: ICP refines on every point of clouds up to this size; larger ones (full-resolution fragments, LiDAR sweeps)
#: are thinned to about this many first (:func:`icp_voxel`): finer than the features' voxel by far, and ICP's
#: time stays bounded.
ICP_POINTS = 50_000


#: Where each cloud's normals are turned to face before its features: a scan in its own frame has its sensor at
#: the origin, and FPFH is not sign-invariant, so normals that face the sensor describe one wall alike in two
#: scans, where unoriented ones flip at random between them (docs/refinement.md). None leaves them as estimated.
VIEWPOINT = (0.0, 0.0, 0.0)


#: Clouds that occupy fewer voxels than this have too few features to match: no estimate.
MIN_VOXELS = 32


#: What each keypoint is described by (:data:`dit_jax.features.descriptors.DESCRIPTORS`).
DESCRIPTOR = "fpfh"


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


def _capped_voxel(points: np.ndarray, voxel: float, most: int) -> float:
    """``voxel``, grown until ``points`` (N, 3) occupy at most about ``most`` of its cells (a surface's count
    falls with the square of the voxel; a few rounds settle clouds whose density varies)."""
    for _ in range(8):
        occupied = occupied_voxels(points, voxel)
        if occupied <= 1.1 * most:
            break
        voxel *= float(np.sqrt(occupied / most))
    return voxel


def icp_voxel(spacing: float, points: int) -> float | None:
    """The grid ICP thins clouds of this point ``spacing`` and at most ``points`` points on, so that a surface
    keeps about :data:`ICP_POINTS` of them; None (every point) for clouds no larger than that."""
    return spacing * float(np.sqrt(points / ICP_POINTS)) if points > ICP_POINTS else None


class Cloud:
    """One cloud as Open3D holds it: its points with normals for ICP (thinned on ``thin``, where given), and the
    points of the features' voxel grid with their ``descriptor`` (:func:`dit_jax.features.descriptors.describe`:
    ``features``, (N, D) float32)."""

    def __init__(
        self, points: np.ndarray, voxel: float, thin: float | None = None, viewpoint=VIEWPOINT, descriptor=DESCRIPTOR
    ):
        o3d = _o3d()
        search = o3d.geometry.KDTreeSearchParamHybrid
        self.full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if thin is not None:
            self.full = self.full.voxel_down_sample(thin)
        self.full.estimate_normals(search(radius=2 * voxel, max_nn=30))  # ICP's: their signs do not matter
        # ICP runs on Open3D's tensor clouds (float64, as the legacy ones): the same point-to-plane ICP with the
        # same motions, in about half the time, and the other direction's work can run beside it.
        self.icp = o3d.t.geometry.PointCloud.from_legacy(self.full, o3d.core.float64)
        self.thinned = self.full.voxel_down_sample(voxel)
        self.thinned.estimate_normals(search(radius=2 * voxel, max_nn=30))
        if viewpoint is not None:
            self.thinned.orient_normals_towards_camera_location(np.asarray(viewpoint, np.float64))
        self.features = descriptors.describe(self.thinned, voxel, descriptor, viewpoint)

    @functools.cached_property
    def tree(self):
        """A k-d tree of the thinned points, built once for the estimator's finalists and :func:`~dit_jax.features.twins.twin_fit`."""
        from scipy.spatial import cKDTree

        return cKDTree(np.asarray(self.thinned.points))


def prepare(src, tgt, spacing: float | None, seed: int, voxel_spacings: float):
    """A pair's clouds src (N, 3) and tgt (M, 3) as float64, their point ``spacing`` (the larger of the two
    where None is given) and the features' voxel at ``voxel_spacings`` spacings (:func:`feature_voxel`), with
    whether that voxel is usable."""
    from dit_jax.geometry import neighbours

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    if spacing is None:
        spacing = max(neighbours.point_spacing(src, seed=seed), neighbours.point_spacing(tgt, seed=seed))
    voxel = feature_voxel(spacing, max(len(src), len(tgt)), voxel_spacings)
    enough = np.isfinite(voxel) and voxel > 0
    if enough:
        voxel = max(_capped_voxel(src, voxel, FEATURE_POINTS), _capped_voxel(tgt, voxel, FEATURE_POINTS))
    enough = enough and all(occupied_voxels(c[:: max(1, len(c) // 4096)], voxel) >= MIN_VOXELS for c in (src, tgt))
    return src, tgt, spacing, voxel, enough


class Scan(NamedTuple):
    """A cloud ready for :func:`~dit_jax.features.matching.register_scans`: its ``points`` (N, 3) float64 and their features (``cloud``)."""

    points: np.ndarray
    cloud: Cloud


@dataclasses.dataclass(frozen=True)
class Scans:
    """Scans of one scene with their features, built once by :func:`prepare_scans` for many pairs: ``scans``,
    or None for a scan too small for features (fewer than :data:`MIN_VOXELS` voxels); ``spacing`` and ``voxel``
    are the scene's, in its units."""

    scans: tuple[Scan | None, ...]
    spacing: float
    voxel: float


def prepare_scans(
    clouds,
    *,
    seed: int = 0,
    viewpoint: tuple | None = VIEWPOINT,
    spacings: list[float] | None = None,
    descriptor: str = DESCRIPTOR,
) -> Scans:
    """Features of K ``clouds`` (each (N_k, 3)) for :func:`~dit_jax.features.matching.register_scans`: as :func:`~dit_jax.features.matching.register_both_ways`
    computes them for a pair, with the largest point spacing and voxel of the scene for every scan, so that each
    scan's features are computed once however many pairs it joins. ``spacings``: each cloud's point spacing
    where the caller has measured it (:func:`dit_jax.geometry.neighbours.point_spacing` with ``seed``)."""
    from dit_jax.geometry import neighbours

    points = [np.asarray(c, np.float64) for c in clouds]
    spacing = max(spacings or [neighbours.point_spacing(p, seed=seed) for p in points])
    most = max(len(p) for p in points)
    voxel = max(_capped_voxel(p, feature_voxel(spacing, most), FEATURE_POINTS) for p in points)
    thin = icp_voxel(spacing, most)
    scans = []
    for p in points:
        enough = occupied_voxels(p[:: max(1, len(p) // 4096)], voxel) >= MIN_VOXELS
        scans.append(Scan(p, Cloud(p, voxel, thin, viewpoint, descriptor)) if enough else None)
    return Scans(tuple(scans), spacing, voxel)
