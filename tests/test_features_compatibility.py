"""dit_jax.features.compatibility: the second-order compatibility estimator on putative matches."""

import jax.numpy as jnp
import numpy as np
import pytest

from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.features import compatibility
from dit_jax.geometry.rigid import rotation_angle_deg


def _outlier_matches(count: int, share_right: float, seed: int):
    """``count`` matches between a 10 m room-sized box of points and its moved copy, ``share_right`` of them right
    (with 1 cm noise), the rest pairing random points of the two clouds; and the motion."""
    rng = np.random.default_rng(seed)
    src = rng.uniform(-5, 5, (count, 3))
    rotation, translation = euler_zyx_to_matrix([120.0, 40.0, -70.0]), np.array([3.0, -7.0, 1.5])
    tgt = src @ rotation.T + translation + rng.normal(scale=0.01, size=src.shape)
    wrong = rng.random(count) >= share_right
    tgt[wrong] = rng.uniform(-5, 5, (wrong.sum(), 3)) @ rotation.T + translation  # anywhere in the target
    return src, tgt, rotation, translation, ~wrong


def test_a_known_motion_is_found_among_95_percent_outlier_matches():
    """2,000 matches, 5 % right: the best hypothesis is the motion to a tenth of a degree and a centimetre, and it
    brings about every right match (and few wrong ones) within the distance."""
    src, tgt, rotation, translation, right = _outlier_matches(2000, 0.05, seed=0)
    found = compatibility.estimate_motions(src, tgt, distance=0.05)
    assert rotation_angle_deg(found.rotation[0].T @ rotation) < 0.1
    assert np.linalg.norm(found.translation[0] - translation) < 0.01
    assert right.sum() - 5 <= found.matches[0] <= right.sum() + 10
    assert np.all(np.diff(found.matches) <= 0)  # best first


def test_far_from_the_origin_and_padded_the_motion_is_the_same():
    """Coordinates a kilometre from the origin (centred before the float32 work), and a count between buckets
    (padded, the padding masked out): the same motion."""
    src, tgt, rotation, translation, _ = _outlier_matches(700, 0.2, seed=1)
    near = compatibility.estimate_motions(src, tgt, distance=0.05)
    far = compatibility.estimate_motions(src + 1000.0, tgt + 1000.0, distance=0.05)
    assert compatibility.bucket(700) == 1024
    assert rotation_angle_deg(far.rotation[0].T @ near.rotation[0]) < 0.01
    far_translation = far.translation[0] + far.rotation[0] @ np.full(3, 1000.0) - 1000.0  # back to the near frame
    np.testing.assert_allclose(far_translation, near.translation[0], atol=1e-3)
    assert far.matches[0] == near.matches[0]


def test_the_compatibility_tables_count_what_they_say():
    """Three matches of one rigid triangle and one stretched match: the first-order table links the three, the
    second-order one counts their common witnesses (one each), and padding rows take part in nothing."""
    src = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [9, 9, 9]])
    tgt = src.at[3].set(jnp.array([0.0, 0, 3]))
    valid = jnp.array([True, True, True, True, False])
    first = compatibility.compatibility(src, tgt, valid, jnp.float32(0.1))
    expected = np.zeros((5, 5))
    expected[:3, :3] = 1 - np.eye(3)
    np.testing.assert_array_equal(first, expected)
    np.testing.assert_array_equal(compatibility.second_order(first), expected)  # each link has one witness
    vector = compatibility.leading_vector(compatibility.second_order(first))
    np.testing.assert_allclose(vector[:3], np.full(3, 1 / np.sqrt(3)), rtol=1e-5)
    assert float(vector[3]) == 0 and float(vector[4]) == 0


def test_too_few_matches_give_the_identity_and_no_nan():
    """Under three matches nothing can be estimated: one identity hypothesis with no matches. Matches that all
    sit on one point give finite motions."""
    few = compatibility.estimate_motions(np.zeros((2, 3)), np.ones((2, 3)), distance=0.1)
    np.testing.assert_array_equal(few.rotation[0], np.eye(3))
    assert few.matches[0] == 0
    same = compatibility.estimate_motions(np.zeros((50, 3)), np.ones((50, 3)), distance=0.1)
    assert np.all(np.isfinite(same.rotation)) and np.all(np.isfinite(same.translation))
    with pytest.raises(ValueError, match="at most"):
        compatibility.estimate_motions(
            np.zeros((compatibility.BUCKETS[-1] + 1, 3)), np.zeros((compatibility.BUCKETS[-1] + 1, 3)), 0.1
        )
