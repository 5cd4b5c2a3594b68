"""The learned descriptor's network: shapes, unit length, chunking, weights in and out, and its place among the
descriptors local features match by."""

import numpy as np
import pytest

from dit_jax.features import descriptors, network

#: The share of keypoints matched to their own place after a turn: measured 0.84 (the histograms 0.91; FPFH,
#: which has no coarse grid to move, 1.0).
RIGHT_AFTER_A_TURN = 0.75


@pytest.fixture(scope="module")
def fresh():
    config = network.DescriptorConfig(width=16, out=8)
    return network.Descriptor(network.init(config, seed=1), config, {"note": "untrained"})


def test_embed_gives_unit_rows_of_the_configured_size(fresh):
    rng = np.random.default_rng(0)
    found = network.embed(fresh, rng.random((300, network.HISTOGRAM_SIZE), np.float32))
    assert found.shape == (300, 8) and found.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(found, axis=1), 1.0, atol=1e-5)


def test_embed_does_not_depend_on_the_chunk_a_row_falls_in(fresh):
    rng = np.random.default_rng(1)
    rows = rng.random((network.CHUNK + 5, network.HISTOGRAM_SIZE), np.float32)
    whole = network.embed(fresh, rows)
    alone = network.embed(fresh, rows[-3:])
    np.testing.assert_allclose(whole[-3:], alone, atol=1e-5)


def test_embed_is_finite_on_zero_rows_and_empty_input(fresh):
    assert np.all(np.isfinite(network.embed(fresh, np.zeros((4, network.HISTOGRAM_SIZE)))))
    assert network.embed(fresh, np.zeros((0, network.HISTOGRAM_SIZE))).shape == (0, 8)


def test_embed_refuses_the_wrong_width_in_one_line(fresh):
    with pytest.raises(ValueError, match=r"must be \(N, 132\)"):
        network.embed(fresh, np.zeros((4, 33)))


def test_weights_round_trip_and_name_a_descriptor(fresh, tmp_path):
    path = network.save(tmp_path / "weights", fresh)
    back = network.load(path)
    assert back.config == fresh.config and back.extra == fresh.extra
    rows = np.random.default_rng(2).random((10, network.HISTOGRAM_SIZE), np.float32)
    np.testing.assert_allclose(network.embed(back, rows), network.embed(fresh, rows), atol=1e-6)
    assert descriptors.is_descriptor(path) and descriptors.is_descriptor("learned")
    assert not descriptors.is_descriptor(str(tmp_path)) and not descriptors.is_descriptor("shot")
    with pytest.raises(FileExistsError):
        network.save(path, fresh)


def test_load_of_a_folder_that_is_not_weights_says_so(tmp_path):
    with pytest.raises(ValueError, match="not a learned descriptor's weights"):
        network.load(tmp_path)


def test_config_refuses_sizes_below_one():
    with pytest.raises(ValueError, match="width"):
        network.DescriptorConfig(width=0)


def test_shipped_weights_match_a_turned_scan(tmp_path):
    """The shipped descriptor matches most keypoints of a wavy sheet to their own place in a turned copy: its
    input does not change with the turn but for the coarse grid of the wide radii."""
    o3d = pytest.importorskip("open3d")
    from dit_jax.features import matching

    rng = np.random.default_rng(3)
    u, v = rng.random((2, 2500))
    points = np.stack([u, v, 0.15 * np.sin(7 * u) * np.cos(5 * v + 3 * u * u)], axis=1)
    turn = o3d.geometry.get_rotation_matrix_from_xyz((0.4, -1.1, 2.0))
    viewpoint = np.array([0.5, 0.5, 3.0])

    def described(cloud_points, sensor):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud_points))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.06, max_nn=30))
        cloud.orient_normals_towards_camera_location(sensor)
        return descriptors.describe(cloud, 0.03, "learned", tuple(sensor))

    first, second = described(points, viewpoint), described(points @ turn.T, turn @ viewpoint)
    assert first.shape == (2500, network.shipped().config.out)
    found = matching._two_nearest(first, second)
    right = np.linalg.norm(points[found.index] - points, axis=1) < 0.03
    assert right.mean() > RIGHT_AFTER_A_TURN
