import jax.numpy as jnp
import numpy as np
import pytest

from dit_jax import baselines, metrics
from dit_jax.data.pairs import euler_zyx_to_matrix

pytest.importorskip("open3d", reason="the baselines need Open3D (pip install 'dit-jax[baselines]')")

# FPFH + RANSAC and FGR work on 0.05-voxel downsampled clouds without refinement: sub-voxel accuracy.
TOLERANCE = {"icp": (0.01, 1e-4), "fpfh_ransac": (2.0, 0.02), "fgr": (2.0, 0.02)}


@pytest.mark.parametrize("name", baselines.NAMES)
def test_identical_clouds_give_the_identity(name, modelnet_shapes):
    x = modelnet_shapes[3][:1000]
    rotation, translation = baselines.get(name)(x, x)
    assert float(metrics.rotation_error_deg(jnp.asarray(rotation), jnp.eye(3))) < 1e-3
    assert np.abs(translation).max() < 1e-5


@pytest.mark.parametrize("name", baselines.NAMES)
def test_clean_pairs_with_small_motion_are_registered(name, modelnet_shapes):
    rot_tol, trans_tol = TOLERANCE[name]
    for index, angles in ((3, [5.0, -3.0, 4.0]), (11, [-2.0, 6.0, 1.0])):
        x = modelnet_shapes[index][:1000]
        r_gt = euler_zyx_to_matrix(np.array(angles))
        t_gt = np.array([0.03, -0.02, 0.05])
        y = (x @ r_gt.T + t_gt)[np.random.default_rng(index).permutation(len(x))]
        rotation, translation = baselines.get(name)(x, y)
        assert float(metrics.rotation_error_deg(jnp.asarray(rotation), jnp.asarray(r_gt))) < rot_tol
        assert np.abs(translation - t_gt).max() < trans_tol
