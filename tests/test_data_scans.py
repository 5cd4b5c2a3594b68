import numpy as np
import pytest
from conftest import SHARED, random_rotation, write_3dmatch_scene, write_scan_series

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
    icp = reg.registration_icp(
        cloud(pair.source), cloud(pair.target), 0.005, truth, reg.TransformationEstimationPointToPoint()
    )
    correction = icp.transformation @ np.linalg.inv(truth)
    moved = np.degrees(np.arccos(np.clip((np.trace(correction[:3, :3]) - 1) / 2, -1, 1)))
    assert moved < 0.5 and icp.fitness > 0.6, (moved, icp.fitness)
    # A wrong pose is not as good: the check can fail.
    wrong = reg.evaluate_registration(cloud(pair.source), cloud(pair.target), 0.005, np.eye(4))
    assert wrong.fitness < icp.fitness - 0.2


def _moved(points, rotation, translation):
    return points @ rotation.T + translation


def test_every_pose_layout_gives_pairs_whose_motion_maps_source_onto_target(tmp_path):
    """3DMatch (fragments and gt.log lists in subfolders), KITTI (poses.txt) and a single pair
    (T_target_source.txt): each pair's motion maps its source exactly onto its target, and each set carries
    its benchmark's criterion."""
    from dit_jax import io

    rng = np.random.default_rng(1)
    world = rng.normal(size=(60, 3))
    # 3DMatch: fragment k holds the world seen from pose k (world = R_k p + t_k); T = inv(pose_i) @ pose_j.
    rooms = tmp_path / "rooms"
    (rooms / "3DMatch").mkdir(parents=True)
    (rooms / "3DLoMatch").mkdir()
    poses = {k: np.vstack([np.c_[random_rotation(rng), rng.normal(size=3)], [0, 0, 0, 1]]) for k in (0, 1, 7)}
    for k, pose in poses.items():
        io.write(rooms / f"cloud_bin_{k}.ply", _moved(world - pose[:3, 3], pose[:3, :3].T, np.zeros(3)))

    def entry(i, j):
        matrix = np.linalg.inv(poses[i]) @ poses[j]
        return f"{i}\t {j}\t 60\t\n" + "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in matrix)

    (rooms / "3DMatch" / "gt.log").write_text(entry(0, 1))
    (rooms / "3DLoMatch" / "gt.log").write_text(entry(0, 7) + entry(1, 7))
    sets = scans.load_pair_sets(rooms)
    assert {k: len(v.pairs) for k, v in sets.items()} == {"3DMatch": 1, "3DLoMatch": 2}
    assert sets["3DLoMatch"].criterion == (15.0, 0.3) and sets["3DLoMatch"].pairs[1].name == "cloud_bin_7->cloud_bin_1"
    # KITTI: scan k in its own frame, poses.txt the frame's pose in the first's (3 x 4 rows).
    drive = tmp_path / "drive"
    drive.mkdir()
    lines = []
    for k in range(3):
        rotation, translation = random_rotation(rng), rng.normal(size=3)
        io.write(drive / f"{k:06d}.ply", _moved(world - translation, rotation.T, np.zeros(3)))
        lines.append(" ".join(f"{v:.17g}" for v in np.c_[rotation, translation].ravel()))
    (drive / "poses.txt").write_text("\n".join(lines) + "\n")
    kitti = scans.load_pair_sets(drive, skips=(1, 2))
    assert [len(kitti[k].pairs) for k in ("skip1", "skip2")] == [2, 1] and kitti["skip1"].criterion == (5.0, 2.0)
    # One pair.
    single = tmp_path / "pair"
    single.mkdir()
    rotation, translation = random_rotation(rng), rng.normal(size=3)
    io.write(single / "source.ply", world)
    io.write(single / "target.pcd", _moved(world, rotation, translation))
    np.savetxt(single / "T_target_source.txt", np.vstack([np.c_[rotation, translation], [0, 0, 0, 1]]))
    one = scans.load_pair_sets(single)["pair"]
    for found in [*sets.values(), *kitti.values(), one]:
        for p in found.pairs:
            # Written as float32: the motion maps the points to within that rounding.
            np.testing.assert_allclose(_moved(p.source, p.rotation, p.translation), p.target, atol=1e-5)


def test_bad_pose_layouts_are_one_clear_error(tmp_path):
    from dit_jax import io

    with pytest.raises(DataError, match="no scan poses found"):
        scans.load_pair_sets(tmp_path)
    (tmp_path / "gt.log").write_text("0 1 2\n1 0 0 0\n")
    with pytest.raises(DataError, match="entries of 5 lines"):
        scans.load_pair_sets(tmp_path)
    (tmp_path / "gt.log").write_text("0 1 2\n" + "1 0 0 0\n" * 4)
    with pytest.raises(DataError, match="no cloud_bin_1"):
        scans.load_pair_sets(tmp_path)
    (tmp_path / "gt.log").unlink()
    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    io.write(tmp_path / "a.ply", np.eye(3))
    with pytest.raises(DataError, match="2 poses for 1 scans"):
        scans.load_pair_sets(tmp_path)


def test_kitchen_fragments_truth_lays_the_overlap_on_itself():
    """The shared 3DMatch fragments: three pairs in two lists, and after the benchmark's truth most source
    points lie within a few centimetres of the target (the overlap), far fewer before it."""
    import pathlib

    from conftest import SHARED
    from scipy.spatial import cKDTree

    folder = pathlib.Path(SHARED) / "data" / "3dmatch_redkitchen"
    if not (folder / "3DMatch" / "gt.log").exists():
        pytest.skip(f"the 3DMatch kitchen fragments are not here ({folder}); they ship with ../shared")
    sets = scans.load_pair_sets(folder)
    assert {k: len(v.pairs) for k, v in sets.items()} == {"3DLoMatch": 2, "3DMatch": 1}
    pair = sets["3DMatch"].pairs[0]
    tree = cKDTree(pair.target)
    sample = pair.source[:: max(1, len(pair.source) // 5000)]
    after = tree.query(_moved(sample, pair.rotation, pair.translation))[0]
    before = tree.query(sample)[0]
    assert np.mean(after < 0.03) > 0.5 > np.mean(before < 0.03), (np.mean(after < 0.03), np.mean(before < 0.03))


THREEDMATCH = SHARED / "data" / "3dmatch"


def test_a_folder_of_3dmatch_scenes_gives_one_set_per_list_with_the_benchmarks_error(tmp_path):
    """Every scene's pairs in one set per list, named by scene; each carries its information matrix, and the
    benchmark's error is 0 at the truth and sqrt(xi' Sigma xi / Sigma_00) off it (quaternion from scipy)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    world = rng.normal(size=(60, 3))
    for name in ("kitchen", "office"):
        write_3dmatch_scene(tmp_path / name, world, rng)
    sets = scans.load_pair_sets(tmp_path)
    assert list(sets) == ["3DMatch"] and sets["3DMatch"].kind == "gt.log"
    pairs = sets["3DMatch"].pairs
    assert [p.name for p in pairs[:3]] == [
        "kitchen/cloud_bin_1->cloud_bin_0",
        "kitchen/cloud_bin_3->cloud_bin_0",
        "kitchen/cloud_bin_3->cloud_bin_1",
    ]
    assert [p.scene for p in pairs] == ["kitchen"] * 3 + ["office"] * 3
    assert [p.consecutive for p in pairs[:3]] == [True, False, False]
    pair = pairs[1]
    np.testing.assert_allclose(pair.source @ pair.rotation.T + pair.translation, pair.target, atol=1e-9)
    assert scans.benchmark_rmse(pair.rotation, pair.translation, pair) < 1e-9
    turn = Rotation.from_rotvec([0.05, -0.02, 0.1]).as_matrix()
    rotation, translation = pair.rotation @ turn, pair.translation + [0.1, 0.0, -0.05]
    error = np.linalg.inv(np.vstack([np.c_[pair.rotation, pair.translation], [0, 0, 0, 1]])) @ np.vstack(
        [np.c_[rotation, translation], [0, 0, 0, 1]]
    )
    xi = np.concatenate([error[:3, 3], Rotation.from_matrix(error[:3, :3]).as_quat()[:3]])
    expected = np.sqrt(xi @ pair.info @ xi / pair.info[0, 0])
    assert scans.benchmark_rmse(rotation, translation, pair) == pytest.approx(expected, rel=1e-9)
    # Near a half turn the quaternion's scalar part vanishes: the other branch gives the same error.
    half = Rotation.from_rotvec([0.0, 0.0, np.pi - 1e-4]).as_matrix()
    xi = np.concatenate([np.zeros(3), Rotation.from_matrix(half).as_quat()[:3]])
    assert scans.benchmark_rmse(pair.rotation @ half, pair.translation, pair) == pytest.approx(
        np.sqrt(xi @ pair.info @ xi / pair.info[0, 0]), rel=1e-6
    )
    (tmp_path / "office" / "3DMatch" / "gt.info").write_text("0 1 60\n1 2 3\n")
    with pytest.raises(DataError, match="gt.info: expected entries of 7 lines"):
        scans.load_pair_sets(tmp_path)


def test_the_shared_3dmatch_scenes_hold_the_benchmarks_pairs():
    """The three shared scenes: 339 3DMatch and 351 3DLoMatch pairs, each with its information matrix, the truth
    at zero error."""
    if not THREEDMATCH.exists():
        pytest.skip(f"the 3DMatch scenes are not here ({THREEDMATCH}); they ship with ../shared")
    sets = scans.load_pair_sets(THREEDMATCH)
    assert {name: len(found.pairs) for name, found in sets.items()} == {"3DMatch": 339, "3DLoMatch": 351}
    assert all(p.info is not None for found in sets.values() for p in found.pairs)
    assert {p.scene for p in sets["3DMatch"].pairs} == {"home_md", "hotel3", "mit_lab"}
    errors = np.array([scans.benchmark_rmse(p.rotation, p.translation, p) for p in sets["3DLoMatch"].pairs])
    # One information matrix of the benchmark's own 3DLoMatch list is all zeros: no error, never registered.
    assert [p.name for p, e in zip(sets["3DLoMatch"].pairs, errors) if np.isnan(e)] == [
        "home_md/cloud_bin_25->cloud_bin_23"
    ]
    assert np.nanmax(errors) < 1e-6


def test_a_scenes_fragments_chain_into_one_frame_through_both_lists():
    """Every pair of both lists is read back from the chained poses; a fragment in no pair is said so."""
    if not THREEDMATCH.is_dir():
        pytest.skip(f"the 3DMatch scenes are not here ({THREEDMATCH}); they ship with ../shared")
    for scene, fragments, unjoined in (("hotel3", 37, []), ("mit_lab", 38, [12])):
        poses, known = scans.scene_poses(THREEDMATCH / scene)
        assert poses.shape == (fragments, 4, 4) and np.flatnonzero(~known).tolist() == unjoined
        np.testing.assert_array_equal(poses[0], np.eye(4))
        for log in sorted((THREEDMATCH / scene).glob("*/gt.log")):
            for i, j, motion in scans.read_gt_log(log):
                np.testing.assert_allclose(np.linalg.inv(poses[i]) @ poses[j], motion, atol=1e-6)
