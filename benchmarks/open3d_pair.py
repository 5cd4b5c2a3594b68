"""The classical registration of one pair with Open3D alone, as a user would script it: the yardstick that
`benchmarks/startup.py` times `dit-register` against.

    python benchmarks/open3d_pair.py examples/chair_src.ply examples/chair_tgt.pcd

Reads both files, estimates normals, computes FPFH features, runs RANSAC on feature matches and refines with
point-to-plane ICP; prints the 4x4 matrix. Lengths are set from the target's size (a twentieth of its
bounding box's diagonal for the features), so any units work.
"""

import sys

import numpy as np
import open3d as o3d

reg = o3d.pipelines.registration
src, tgt = (o3d.io.read_point_cloud(path) for path in sys.argv[1:3])
voxel = np.linalg.norm(tgt.get_max_bound() - tgt.get_min_bound()) / 20
features = []
for cloud in (src, tgt):
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    features.append(reg.compute_fpfh_feature(cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)))
found = reg.registration_ransac_based_on_feature_matching(
    src, tgt, *features, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
    [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
    reg.RANSACConvergenceCriteria(100_000, 0.999),
)  # fmt: skip
refined = reg.registration_icp(src, tgt, 0.4 * voxel, found.transformation, reg.TransformationEstimationPointToPlane())
np.set_printoptions(precision=6, suppress=True)
print(refined.transformation)
