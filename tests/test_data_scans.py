import numpy as np
import pytest

from conftest import random_rotation, write_scan_series
from dit_jax.data import scans
from dit_jax.data.shapes import DataError


def test_quaternion_matrix_matches_scipy():
    from scipy.spatial.transform import Rotation

    q = np.array([0.1, -0.4, 0.3, 0.85])
    np.testing.assert_allclose(scans.quaternion_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)


def test_pairs_carry_the_motion_between_scans(tmp_path):
    rng = np.random.default_rng(0)
    poses = [(random_rotation(rng), rng.normal(size=3)) for _ in range(4)]
    write_scan_series(tmp_path, poses, rng)
    series = scans.load_scans(tmp_path)
    assert [s.name for s in series] == ["s0", "s1", "s2", "s3"], "bmesh lines only, in order"
    for skip in (1, 2):
        pairs = scans.scan_pairs(series, skip)
        assert len(pairs) == 4, "cyclic: as many pairs as scans"
        for p in pairs:
            # The same physical points: the motion maps the source scan exactly onto the target scan.
            np.testing.assert_allclose(p.source @ p.rotation.T + p.translation, p.target, atol=1e-9)


def test_bad_conf_is_one_clear_error(tmp_path):
    (tmp_path / "a.conf").write_text("bmesh a.ply 0 0 0 0 0 0\n")
    with pytest.raises(DataError, match=r"a.conf:1: expected 'bmesh FILE"):
        scans.load_scans(tmp_path)
    (tmp_path / "a.conf").write_text("bmesh missing.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match="lists missing.ply"):
        scans.load_scans(tmp_path)
    with pytest.raises(DataError, match="no such directory"):
        scans.load_scans(tmp_path / "nowhere")


def test_dragon_truth_agrees_with_icp(dragon_dir):
    """The poses of the .conf register two adjacent real scans: ICP started at the truth moves less than
    half a degree and lays most of the source onto the target."""
    o3d = pytest.importorskip("open3d", reason="ICP comes from Open3D (the baselines extra)")
    series = scans.load_scans(dragon_dir)
    assert len(series) == 15 and all(len(s.points) > 10_000 for s in series)
    pair = scans.scan_pairs(series, 1)[0]
    angle = np.degrees(np.arccos((np.trace(pair.rotation) - 1) / 2))
    assert 23 < angle < 25, "the turntable turns 24 degrees a step"
    cloud = lambda p: o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(0.002)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = pair.rotation, pair.translation
    reg = o3d.pipelines.registration
    icp = reg.registration_icp(cloud(pair.source), cloud(pair.target), 0.005, truth,
                               reg.TransformationEstimationPointToPoint())
    correction = icp.transformation @ np.linalg.inv(truth)
    moved = np.degrees(np.arccos(np.clip((np.trace(correction[:3, :3]) - 1) / 2, -1, 1)))
    assert moved < 0.5 and icp.fitness > 0.6, (moved, icp.fitness)
    # A wrong pose is not as good: the check can fail.
    wrong = reg.evaluate_registration(cloud(pair.source), cloud(pair.target), 0.005, np.eye(4))
    assert wrong.fitness < icp.fitness - 0.2
