"""dit_jax.features.matching: registration by local features (FPFH, the compatibility estimator, Open3D's ICP)."""

import numpy as np
import pytest
from conftest import box_room

from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.features import keypoints, matching
from dit_jax.geometry.rigid import rotation_angle_deg
from dit_jax.pipeline import verdict

pytest.importorskip("open3d")


def _surface(n: int, seed: int) -> np.ndarray:
    """An independent sampling of one bumpy closed surface. No turn maps it onto itself: the last term breaks
    the half turn about x that the first two allow."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    bumps = 0.3 * np.sin(6 * d[:, :1]) * np.cos(5 * d[:, 1:2]) + 0.1 * d[:, 2:] ** 2
    return d * (1 + bumps + 0.15 * np.sin(3 * d[:, 1:2] + 2 * d[:, 2:]))


def test_two_samplings_of_a_surface_half_a_turn_apart_register_the_same_in_any_units():
    """No start needed: 150 degrees apart. The clouds are not in a sensor's frame, so their normals are left
    unoriented (``viewpoint=None``). The global estimate alone lands near the truth, and ICP after it within half a
    degree; in millimetres the refined motion is the same, since every length comes from the point spacing."""
    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    truth, t_truth = euler_zyx_to_matrix([150.0, -30.0, 20.0]), np.array([2.0, -1.0, 0.5])
    tgt = other @ truth.T + t_truth
    coarse = matching.match_one_way(src, tgt, viewpoint=None)
    assert coarse.inliers > 0
    assert rotation_angle_deg(coarse.rotation.T @ truth) < 10.0
    assert np.linalg.norm(coarse.translation - t_truth) < 5 * coarse.voxel
    metres = matching.register_both_ways(src, tgt, viewpoint=None)
    millimetres = matching.register_both_ways(src * 1000, tgt * 1000, viewpoint=None)
    assert rotation_angle_deg(metres.kept[0].T @ truth) < 0.5
    assert rotation_angle_deg(millimetres.kept[0].T @ metres.kept[0]) < 0.1
    np.testing.assert_allclose(millimetres.kept[1] / 1000, metres.kept[1], atol=0.01)
    assert millimetres.voxel == pytest.approx(1000 * metres.voxel, rel=1e-6)


def test_the_voxel_follows_the_spacing_and_grows_with_the_cloud():
    assert keypoints.feature_voxel(0.01, 5_000) == pytest.approx(0.01 * keypoints.VOXEL_SPACINGS)
    big = 100 * keypoints.FEATURE_POINTS
    assert keypoints.feature_voxel(0.01, big) == pytest.approx(0.1)  # sqrt(100) spacings


def test_a_cloud_without_features_gives_the_identity_and_no_nan():
    """Points on a plane carry no 3-D features: whatever the matcher finds, the answer is finite, and a
    failure reads as no inliers and the identity."""
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)]
    found = matching.match_one_way(plane, plane + [0.1, 0.0, 0.0])
    assert np.all(np.isfinite(found.rotation)) and np.all(np.isfinite(found.translation))
    np.testing.assert_allclose(found.rotation @ found.rotation.T, np.eye(3), atol=1e-5)
    if found.inliers == 0:
        np.testing.assert_array_equal(found.rotation, np.eye(3))


def test_a_few_points_give_no_estimate_instead_of_a_crash():
    """Clouds that occupy fewer than MIN_VOXELS voxels have too few features to match: no estimate."""
    rng = np.random.default_rng(0)
    few = rng.normal(size=(3, 3))
    found = matching.match_one_way(few, few + 0.1)
    assert found.inliers == 0 and np.array_equal(found.rotation, np.eye(3))
    assert matching.register_both_ways(few, few + 0.1) is None
    assert keypoints.occupied_voxels(few, 10.0) == 1


def test_both_ways_agree_on_a_true_motion_and_stay_finite_on_a_featureless_sphere():
    """The evidence the verdict reads: two independent samplings of a bumpy surface, half a turn apart, give
    one motion both ways (within the pipeline's default bounds, 1 degree and 2 spacings) that is right; a featureless sphere gives
    no motion to trust, and no NaN either."""
    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    truth, t_truth = euler_zyx_to_matrix([150.0, -30.0, 20.0]), np.array([2.0, -1.0, 0.5])
    found = matching.register_both_ways(src, other @ truth.T + t_truth, viewpoint=None)
    assert verdict.features_agree(found, 1.0, 2.0) and min(found.inliers) > 0 and found.seconds > 0
    rotation, translation = found.kept
    assert rotation_angle_deg(rotation.T @ truth) < 2.0 and np.linalg.norm(translation - t_truth) < 4 * found.spacing
    assert found.overlap.shape == (2,) and np.all((0 <= found.overlap) & (found.overlap <= 1))
    d = np.random.default_rng(3).normal(size=(8000, 3))
    sphere = d / np.linalg.norm(d, axis=1, keepdims=True)
    e = np.random.default_rng(4).normal(size=(8000, 3))
    turned = (e / np.linalg.norm(e, axis=1, keepdims=True)) @ euler_zyx_to_matrix([40.0, 0.0, 0.0]).T
    spun = matching.register_both_ways(sphere, turned)
    assert spun is not None and np.isfinite(spun.disagreement) and np.isfinite(spun.offset)


def test_the_estimate_repeats_exactly_and_each_feature_finds_its_two_nearest_both_ways():
    """No random draws: the same pair gives the same motion on every run. The blocked products find, both
    ways, every feature's nearest and second nearest with their distances, as a brute-force search does, across
    blocks of rows too."""
    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    tgt = other @ euler_zyx_to_matrix([150.0, -30.0, 20.0]).T
    runs = [matching.match_one_way(src, tgt) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].rotation, runs[1].rotation)
    assert runs[0].inliers == runs[1].inliers > 0
    rng = np.random.default_rng(0)
    queries, pool = rng.normal(size=(70, 33)).astype(np.float32), rng.normal(size=(45, 33)).astype(np.float32)
    distances = np.linalg.norm(queries[:, None].astype(np.float64) - pool[None], axis=2)
    for found, table in (
        (matching._two_nearest(queries, pool, block=16), distances),
        (matching._two_nearest(pool, queries, block=16), distances.T),
    ):
        ranked = np.sort(table, axis=1)
        np.testing.assert_array_equal(found.index, np.argmin(table, axis=1))
        np.testing.assert_allclose(found.nearest, ranked[:, 0], rtol=1e-4)
        np.testing.assert_allclose(found.second, ranked[:, 1], rtol=1e-4)
        np.testing.assert_allclose(found.ratio, ranked[:, 0] / ranked[:, 1], rtol=1e-4)
        assert np.all(found.ratio <= 1)


def test_matches_past_the_cap_keep_the_most_distinctive(monkeypatch):
    """Where a direction has more matches than the cap, those whose nearest feature stands out from the second
    nearest are kept, not the closest: a target feature repeated twice is an ambiguous match however close."""

    class Cloud:
        def __init__(self, rows):
            self.features = np.asarray(rows, np.float32)

    rng = np.random.default_rng(3)
    pool = rng.normal(size=(40, 33))
    pool[20:30] = pool[10:20]  # features 10-19 each have a twin: two nearest at one distance
    queries = pool[:30] + 0.01 * rng.normal(size=(30, 33))
    queries[10:20] = pool[10:20] + 0.001 * rng.normal(size=(10, 33))  # the closest matches, but ambiguous
    monkeypatch.setattr(matching, "MAX_MATCHES", 10)
    there, _ = matching._matches(Cloud(queries), Cloud(pool))
    np.testing.assert_array_equal(there, np.stack([np.arange(10), np.arange(10)], axis=1))


def test_a_box_room_fits_its_quarter_turned_twin_and_a_bumpy_surface_does_not():
    """twin_fit: in a bare box room the true motion turned a quarter about the floor's normal lays as many
    points on the target as the motion itself (share about 1); a blob with no symmetry (near a sphere, so its
    twins still lay 0.6 of its points within RANSAC's distance) stays under the pipeline's bound of 0.8."""
    truth, t_truth = euler_zyx_to_matrix([30.0, 0.0, 0.0]), np.array([0.3, -0.2, 0.0])
    room = matching.register_both_ways(box_room(30000, 1), box_room(30000, 2) @ truth.T + t_truth)
    assert room.twin_fit((truth, t_truth)) > 0.95 and min(room.twin) > 0.95
    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    truth, t_truth = euler_zyx_to_matrix([150.0, -30.0, 20.0]), np.array([2.0, -1.0, 0.5])
    bumpy = matching.register_both_ways(src, other @ truth.T + t_truth, viewpoint=None)
    assert bumpy.twin_fit((truth, t_truth)) < 0.75 and max(bumpy.twin) < 0.75
    assert verdict.features_agree(bumpy, 1.0, 2.0, max_twin=0.8) and not verdict.features_agree(
        room, 1.0, 2.0, max_twin=0.8
    )


def test_icp_on_tensor_clouds_gives_the_legacy_motion_and_large_clouds_are_thinned_for_it():
    """ICP runs on Open3D's tensor clouds: the same point-to-plane ICP as the legacy call, started alike, lands
    on the same motion. Clouds over ICP_POINTS are thinned for ICP, smaller ones not."""
    from dit_jax.geometry.neighbours import point_spacing

    o3d = matching._o3d()
    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    truth = euler_zyx_to_matrix([10.0, -5.0, 3.0])
    voxel = 0.08
    source, target = keypoints.Cloud(src, voxel), keypoints.Cloud(other @ truth.T + 0.05, voxel)
    start = np.eye(4)
    reg = o3d.pipelines.registration
    legacy = reg.registration_icp(
        source.full, target.full, 0.4 * voxel, start, reg.TransformationEstimationPointToPlane()
    ).transformation
    np.testing.assert_allclose(matching._icp(source, target, start, voxel), legacy, atol=1e-6)
    assert keypoints.icp_voxel(0.01, keypoints.ICP_POINTS) is None
    assert keypoints.icp_voxel(0.01, 4 * keypoints.ICP_POINTS) == pytest.approx(0.02)
    big = _surface(4 * keypoints.ICP_POINTS, seed=3)
    thinned = keypoints.Cloud(big, voxel, keypoints.icp_voxel(point_spacing(big), len(big)))
    # A scan's even sampling keeps about ICP_POINTS (the kitchen fragments: 58,000 of 260,000); a random one more.
    assert len(thinned.full.points) < 0.75 * len(big) and len(source.full.points) == len(src)


def test_normals_face_the_viewpoint_before_features_and_are_left_alone_without_one():
    """A scan in its sensor's frame: every thinned point's normal is turned to face the origin (its sensor);
    with ``viewpoint=None`` the signs are Open3D's, and some face away."""
    src = box_room(20000, 1)  # the origin lies inside the room, as a scanner's would
    voxel = 0.1
    facing = keypoints.Cloud(src, voxel)
    towards = -np.asarray(facing.thinned.points)  # from each point to the origin
    assert np.all(np.einsum("ij,ij->i", np.asarray(facing.thinned.normals), towards) >= 0)
    as_estimated = keypoints.Cloud(src, voxel, viewpoint=None)
    signs = np.einsum("ij,ij->i", np.asarray(as_estimated.thinned.normals), towards)
    assert np.mean(signs < 0) > 0.05


def test_scans_prepared_once_register_each_pair_as_the_pair_alone_does():
    """A scene's scans are prepared once (:func:`keypoints.prepare_scans`); a pair of them then registers
    exactly as :func:`register_both_ways` registers the two clouds alone, where the two share the scene's
    spacing and voxel (as two scans of one set do)."""
    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    truth, t_truth = euler_zyx_to_matrix([150.0, -30.0, 20.0]), np.array([2.0, -1.0, 0.5])
    tgt = other @ truth.T + t_truth
    prepared = keypoints.prepare_scans([src, tgt], viewpoint=None)
    alone = matching.register_both_ways(src, tgt, viewpoint=None)
    from_scans = matching.register_scans(prepared, 0, 1)
    assert prepared.voxel == pytest.approx(alone.voxel) and prepared.spacing == pytest.approx(alone.spacing)
    for mine, theirs in ((from_scans.forward, alone.forward), (from_scans.backward, alone.backward)):
        np.testing.assert_allclose(mine[0], theirs[0], atol=1e-9)
        np.testing.assert_allclose(mine[1], theirs[1], atol=1e-9)
    assert from_scans.inliers == alone.inliers
    few = np.random.default_rng(0).normal(size=(3, 3))
    with_few = keypoints.prepare_scans([src, few])
    assert with_few.scans[1] is None and matching.register_scans(with_few, 0, 1) is None
