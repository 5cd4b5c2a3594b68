"""Classical registration baselines through Open3D (the ``baselines`` extra), on the same pairs as DIT.

Each baseline maps ``(src (N, 3), tgt (M, 3))`` to ``(R (3, 3), t (3,))`` with ``tgt ~ R src + t``. Parameters
(for unit-sphere shapes, as in ModelNet40 and the embedded set):

* ``icp``: point-to-point ICP from the identity, max correspondence distance 0.2, at most 100 iterations.
* ``fpfh_ransac``: voxel 0.05 downsampling, normals from 30 neighbours within 0.1, FPFH (radius 0.25, 100
  neighbours), RANSAC on mutual feature matches with 3 points, distance 0.075, edge-length check 0.9,
  100,000 iterations at confidence 0.999.
* ``fgr``: fast global registration on the same FPFH features, max correspondence distance 0.075.

The random parts of RANSAC are seeded (``open3d.utility.random.seed(0)``) so the figures repeat.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

VOXEL = 0.05
NAMES = ("icp", "fpfh_ransac", "fgr")


def _o3d():
    try:
        import open3d as o3d
    except ImportError:
        raise ImportError("the baselines need Open3D: pip install 'dit-jax[baselines]' "
                          "(and on Debian: apt-get install libusb-1.0-0)") from None
    return o3d


def _cloud(points: np.ndarray):
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64))
    return cloud


def _split(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    transform = np.asarray(transform)
    return transform[:3, :3].astype(np.float32), transform[:3, 3].astype(np.float32)


def icp(src: np.ndarray, tgt: np.ndarray, max_distance: float = 0.2, max_iterations: int = 100):
    o3d = _o3d()
    reg = o3d.pipelines.registration
    result = reg.registration_icp(_cloud(src), _cloud(tgt), max_distance, np.eye(4),
                                  reg.TransformationEstimationPointToPoint(),
                                  reg.ICPConvergenceCriteria(max_iteration=max_iterations))
    return _split(result.transformation)


def _features(points: np.ndarray, voxel: float = VOXEL):
    o3d = _o3d()
    down = _cloud(points).voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return down, fpfh


def fpfh_ransac(src: np.ndarray, tgt: np.ndarray, voxel: float = VOXEL):
    o3d = _o3d()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(0)
    (s, sf), (t, tf) = _features(src, voxel), _features(tgt, voxel)
    distance = 1.5 * voxel
    result = reg.registration_ransac_based_on_feature_matching(
        s, t, sf, tf, True, distance, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    return _split(result.transformation)


def fgr(src: np.ndarray, tgt: np.ndarray, voxel: float = VOXEL):
    o3d = _o3d()
    reg = o3d.pipelines.registration
    (s, sf), (t, tf) = _features(src, voxel), _features(tgt, voxel)
    result = reg.registration_fgr_based_on_feature_matching(
        s, t, sf, tf, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=1.5 * voxel))
    return _split(result.transformation)


def get(name: str) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    if name not in NAMES:
        raise ValueError(f"unknown baseline {name!r}; choose from {', '.join(NAMES)}")
    return {"icp": icp, "fpfh_ransac": fpfh_ransac, "fgr": fgr}[name]


def available() -> bool:
    try:
        _o3d()
    except ImportError:
        return False
    return True
