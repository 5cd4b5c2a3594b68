import json
import pathlib

import jax.numpy as jnp
import numpy as np
import pytest

from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.evaluators import baselines, metrics, scene_baselines

pytest.importorskip("open3d", reason="the baselines need Open3D (pip install 'dit-jax[baselines]')")

# Global estimates alone are as good as their matches (possibly on a downsampled cloud); refined by ICP on
# identical points they are exact.
TOLERANCE = {
    "icp": (0.01, 1e-4),
    "fpfh_ransac": (2.0, 0.02),
    "fgr": (2.0, 0.02),
    "fpfh_ransac_icp": (0.01, 1e-4),
    "fgr_icp": (0.01, 1e-4),
}


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


def test_every_method_and_setting_has_tuned_options_recorded_in_docs():
    """The shipped choice (python tools/tune_baselines.py) covers every baseline, every setting and "any"."""
    from dit_jax.data.pairs import SETTINGS

    choice = baselines.tuned()
    assert set(baselines.NAMES) <= set(choice)
    for name in baselines.NAMES:
        assert set(choice[name]) == {*SETTINGS, "any"}
        for setting in SETTINGS:
            assert baselines.tuned_options(name, setting) == baselines.Options.from_dict(choice[name][setting])
        assert baselines.tuned_options(name, "a setting never tuned") == baselines.Options.from_dict(
            choice[name]["any"]
        )
    with pytest.raises(ValueError, match="unknown baseline"):
        baselines.tuned_options("ransac")


def test_refine_option_refines_as_dit_does(modelnet_shapes):
    """``icp_method="refine"`` is DIT+ICP's refinement (dit_jax.geometry.icp_refine.refine), the schedule fields unused; the
    shipped choice uses it only where tools/compare_baseline_refinement.py recorded why."""
    from dit_jax.geometry import icp, icp_refine

    rng = np.random.default_rng(4)
    x = modelnet_shapes[5][:1000].astype(np.float64)
    r_gt = euler_zyx_to_matrix(np.array([20.0, -10.0, 15.0]))
    y = x[rng.permutation(1000)[:800]] @ r_gt.T + np.array([0.1, 0.0, -0.05]) + rng.normal(0, 0.01, (800, 3))
    start = euler_zyx_to_matrix(np.array([23.0, -8.0, 13.0])), np.array([0.12, 0.02, -0.05])
    options = baselines.Options(icp_method=baselines.REFINE, icp_distances=(0.5,), icp_iterations=1)
    rotation, translation = baselines.refine(x, y, *start, options)
    expected = icp_refine.refine(x, y, *start)
    np.testing.assert_array_equal(rotation, expected.rotation)
    np.testing.assert_array_equal(translation, expected.translation)
    assert float(metrics.rotation_error_deg(jnp.asarray(rotation), jnp.asarray(r_gt))) < 1.0

    tuned = json.loads((pathlib.Path(baselines.__file__).parent / baselines.TUNED_FILE).read_text())
    for name in ("fpfh_ransac_icp", "fgr_icp"):
        for target, chosen in tuned["choice"][name].items():
            assert chosen["icp_method"] in (*icp.METHODS, baselines.REFINE)
            if chosen["icp_method"] == baselines.REFINE:
                assert tuned["refinement"]["single_icp_method"][name][target] in icp.METHODS


def test_options_round_trip_and_explicit_options_win():
    options = baselines.Options(voxel=0.03, icp_distances=(0.2, 0.05))
    assert baselines.Options.from_dict(options.to_dict()) == options
    assert baselines.get("fgr", "clean", options).keywords["options"] is options


def test_dense_clouds_are_downsampled_for_features(modelnet_shapes):
    dense = np.repeat(modelnet_shapes[3], 6, axis=0) + np.random.default_rng(0).normal(0, 0.002, (6 * 1024, 3))
    cloud, _ = baselines.features(dense, baselines.Options())
    assert len(dense) > baselines.DENSE_POINTS and len(cloud.points) < len(dense) / 3


def test_open3d_multiway_places_views_of_one_surface_in_the_first_one_s_frame():
    """The scenes' baseline: three independent samplings of one bumpy surface, each in its own frame, come back
    as poses into scan 0's frame close to the truth."""
    from dit_jax.geometry.rigid import rotation_angle_deg

    poses, clouds = [], []
    for k in range(3):
        d = np.random.default_rng(k).normal(size=(6000, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        surface = d * (1 + 0.3 * np.sin(6 * d[:, :1]) * np.cos(5 * d[:, 1:2]) + 0.1 * d[:, 2:] ** 2)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = euler_zyx_to_matrix([20.0 * k, 5.0 * k, -10.0 * k]), [0.2 * k, 0.0, 0.1]
        poses.append(pose)
        clouds.append((surface - pose[:3, 3]) @ pose[:3, :3])  # the surface seen from pose k
    counted, pairs = [], []
    found = scene_baselines.open3d_multiway(clouds, voxel=0.05, on_pair=counted.append, on_result=pairs.append)
    assert found.shape == (3, 4, 4) and sum(counted) == 3
    for k in range(3):
        expected = np.linalg.inv(poses[0]) @ poses[k]
        assert rotation_angle_deg(found[k][:3, :3].T @ expected[:3, :3]) < 2.0
        assert np.linalg.norm(found[k][:3, 3] - expected[:3, 3]) < 0.05
    # A stopped run resumes: the pairs it logged (as JSON and back) are taken as they are, the rest registered.
    assert sorted((p.source, p.target) for p in pairs) == [(0, 1), (0, 2), (1, 2)]
    logged = [scene_baselines.MultiwayPair.from_record(json.loads(json.dumps(p.to_record()))) for p in pairs[:2]]
    assert all(np.array_equal(a.information, b.information) and a.seconds == b.seconds for a, b in zip(logged, pairs))
    counted, more = [], []
    known = {(p.source, p.target): p for p in logged}
    again = scene_baselines.open3d_multiway(
        clouds, voxel=0.05, on_pair=counted.append, known=known, on_result=more.append
    )
    assert counted == [2, 1] and [(p.source, p.target) for p in more] == [(pairs[2].source, pairs[2].target)]
    for k in range(3):  # RANSAC runs in threads: the pair registered again need not repeat its last digits
        expected = np.linalg.inv(poses[0]) @ poses[k]
        assert rotation_angle_deg(again[k][:3, :3].T @ expected[:3, :3]) < 2.0
        assert np.linalg.norm(again[k][:3, 3] - expected[:3, 3]) < 0.05
