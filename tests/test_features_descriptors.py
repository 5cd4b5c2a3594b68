"""dit_jax.features.descriptors: FPFH at one radius and the joined, square-rooted histograms."""

import numpy as np
import pytest
from conftest import box_room

from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.features import descriptors, keypoints, matching
from dit_jax.geometry.rigid import rotation_angle_deg

pytest.importorskip("open3d")


def _keypoints(points: np.ndarray, voxel: float, viewpoint=(0.0, 0.0, 0.0)):
    """The keypoints as local features build them: the cloud on a grid of ``voxel``, normals facing ``viewpoint``."""
    return keypoints.Cloud(points, voxel, viewpoint=viewpoint, descriptor="fpfh").thinned


def _bumpy_room(seed: int) -> np.ndarray:
    """A room with a table and a box on its floor, seen from inside (the origin): no turn maps it onto itself."""
    rng = np.random.default_rng(seed)
    room = box_room(24_000, seed)
    table = np.c_[rng.uniform(-1.5, -0.3, (3000, 2)), np.full(3000, 0.8)]
    box = rng.uniform(0, 1, (3000, 3)) * [0.5, 0.8, 0.6] + [0.6, 0.4, 0.0]
    box[np.arange(3000) % 3 == 0, 2] = 0.6  # its top
    return np.concatenate([room, table, box]) - [0.0, 0.0, 1.2]


def test_histograms_join_four_unit_blocks_of_square_rooted_fpfh_and_fpfh_stays_as_open3d_gives_it():
    cloud = _keypoints(_bumpy_room(0), 0.1)
    joined = descriptors.describe(cloud, 0.1, "histograms", (0.0, 0.0, 0.0))
    assert joined.shape == (len(cloud.points), 33 * len(descriptors.BLOCKS)) and joined.dtype == np.float32
    norms = np.linalg.norm(joined.reshape(len(joined), len(descriptors.BLOCKS), 33), axis=2)
    np.testing.assert_allclose(norms[norms > 0], 1.0, rtol=1e-5)
    single = descriptors.describe(cloud, 0.1, "fpfh")
    assert single.shape == (len(cloud.points), 33)
    # each of FPFH's three histograms sums to 200 (Open3D's scale); the block at FPFH's own radius is its square
    # root, scaled
    np.testing.assert_allclose(single.reshape(-1, 3, 11).sum(axis=2), 200.0, rtol=1e-4)
    own = list(descriptors.BLOCKS).index(descriptors.Block(descriptors.FPFH_RADIUS, 1.0, descriptors.FPFH_NEIGHBOURS))
    block = joined[:, 33 * own : 33 * own + 33]
    expected = np.sqrt(single) / np.linalg.norm(np.sqrt(single), axis=1, keepdims=True)
    np.testing.assert_allclose(block, expected, atol=1e-5)


def test_fpfh_is_the_default_and_an_unknown_descriptor_is_refused():
    cloud = _keypoints(_bumpy_room(0), 0.1)
    assert descriptors.describe(cloud, 0.1).shape[1] == 33
    assert keypoints.DESCRIPTOR == "fpfh" and descriptors.DESCRIPTORS[0] == "fpfh"
    with pytest.raises(ValueError, match="descriptor must be one of"):
        descriptors.describe(cloud, 0.1, "shot")


def test_a_point_alone_gets_zeros_not_nan():
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-1, 1, (4000, 2)) @ [[1, 0, 0], [0, 1, 0]], [[0.0, 0.0, 50.0]]])
    cloud = _keypoints(points + [0, 0, 2.0], 0.05)
    joined = descriptors.describe(cloud, 0.05, "histograms", (0.0, 0.0, 0.0))
    assert np.all(np.isfinite(joined))
    alone = np.argmax(np.asarray(cloud.points)[:, 2])
    assert np.all(joined[alone] == 0)  # no neighbour within any radius


def test_the_histograms_are_the_same_in_millimetres_and_match_a_turned_copy_of_the_room_better_than_fpfh():
    """Every radius is in voxels: scaled clouds and voxel give the same descriptors. Turned about the sensor
    (normals still face it), a room's keypoints find their own turned selves by nearest descriptor; the joined
    histograms find more of them than FPFH at one radius (the grids differ after the turn, as two scans' do)."""
    points = _bumpy_room(1)
    metres = descriptors.describe(_keypoints(points, 0.1), 0.1, "histograms", (0.0, 0.0, 0.0))
    millimetres = descriptors.describe(_keypoints(points * 1000, 100.0), 100.0, "histograms", (0.0, 0.0, 0.0))
    assert metres.shape == millimetres.shape
    assert np.mean(np.abs(metres - millimetres)) < 1e-3
    turn = euler_zyx_to_matrix([70.0, 20.0, -10.0])
    share = {}
    for name in ("fpfh", "histograms"):
        here, there = _keypoints(points, 0.1), _keypoints(points @ turn.T, 0.1)
        found = matching._two_nearest(
            descriptors.describe(here, 0.1, name, (0.0, 0.0, 0.0)),
            descriptors.describe(there, 0.1, name, (0.0, 0.0, 0.0)),
        )
        moved = np.asarray(here.points) @ turn.T
        share[name] = np.mean(np.linalg.norm(moved - np.asarray(there.points)[found.index], axis=1) < 0.2)
    assert share["histograms"] > share["fpfh"] and share["histograms"] > 0.3, share


def test_a_surface_seen_from_its_centre_registers_by_the_histograms_half_a_turn_apart():
    """Normals that face a viewpoint (here each cloud's centre) are what the histograms need; the pair registers
    from them without a start, 150 degrees apart."""
    from test_features_matching import _surface

    src, other = _surface(8000, seed=1), _surface(8000, seed=2)
    truth = euler_zyx_to_matrix([150.0, -30.0, 20.0])
    found = matching.match_one_way(src, other @ truth.T, viewpoint=(0.0, 0.0, 0.0), descriptor="histograms")
    assert found.inliers > 0 and rotation_angle_deg(found.rotation.T @ truth) < 1.0
