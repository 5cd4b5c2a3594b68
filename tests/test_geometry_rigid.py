import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_rotation

from dit_jax.geometry import rigid


def test_knn_equals_brute_force_numpy():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(200, 3)).astype(np.float32)
    idx = np.asarray(rigid.knn(jnp.asarray(points), 12))
    dist = ((points[:, None, :].astype(np.float64) - points[None, :, :]) ** 2).sum(-1)
    expected = np.argsort(dist, axis=1, kind="stable")[:, :12]
    np.testing.assert_array_equal(idx, expected)
    assert (idx[:, 0] == np.arange(200)).all(), "each point is its own first neighbour"


def test_knn_rejects_too_few_points():
    with pytest.raises(ValueError, match="at least k=20"):
        rigid.knn(jnp.zeros((10, 3)), 20)


def test_gather_neighbours_is_neighbour_major():
    features = jnp.arange(12.0).reshape(4, 3)
    idx = jnp.array([[0, 2], [1, 3], [2, 0], [3, 1]])
    out = rigid.gather_neighbours(features, idx)
    np.testing.assert_array_equal(out[0], features[jnp.array([0, 2])])


def _rigid_pair(rng, n=100, planar=False):
    src = rng.normal(size=(n, 3))
    if planar:
        src[:, 2] = 0.0
    rot = random_rotation(rng)
    trans = rng.uniform(-0.5, 0.5, size=3)
    return src.astype(np.float32), (src @ rot.T + trans).astype(np.float32), rot, trans


@pytest.mark.parametrize("planar", [False, True], ids=["general", "coplanar"])
def test_procrustes_recovers_known_transform(planar):
    # Coplanar points leave the SVD's third direction free: its sign often makes U V^T a reflection, which
    # the determinant correction must turn back into the rotation.
    rng = np.random.default_rng(1)
    for _ in range(20):
        src, tgt, rot, trans = _rigid_pair(rng, planar=planar)
        r, t = rigid.weighted_procrustes(jnp.asarray(src), jnp.asarray(tgt), jnp.ones(len(src)))
        np.testing.assert_allclose(np.asarray(r), rot, atol=1e-6)
        np.testing.assert_allclose(np.asarray(t), trans, atol=1e-6)


def test_procrustes_returns_rotation_for_mirrored_target():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3)).astype(np.float32)
    tgt = src * np.array([1, 1, -1], np.float32)  # a reflection: no rotation maps src onto it
    r, _ = rigid.weighted_procrustes(jnp.asarray(src), jnp.asarray(tgt), jnp.ones(50))
    assert np.linalg.det(np.asarray(r)) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(np.asarray(r) @ np.asarray(r).T, np.eye(3), atol=1e-5)


def test_procrustes_ignores_zero_weight_outliers():
    rng = np.random.default_rng(3)
    src, tgt, rot, trans = _rigid_pair(rng)
    tgt[:30] = rng.normal(size=(30, 3)) * 5
    weights = np.ones(len(src), np.float32)
    weights[:30] = 0
    r, t = rigid.weighted_procrustes(jnp.asarray(src), jnp.asarray(tgt), jnp.asarray(weights))
    np.testing.assert_allclose(np.asarray(r), rot, atol=1e-5)
    np.testing.assert_allclose(np.asarray(t), trans, atol=1e-5)


@pytest.mark.parametrize("case", ["zero_weights", "identical_points", "collinear", "one_weighted_point"])
def test_procrustes_degenerate_input_is_finite(case):
    rng = np.random.default_rng(4)
    src = rng.normal(size=(40, 3)).astype(np.float32)
    tgt = src + 1.0
    weights = np.ones(40, np.float32)
    if case == "zero_weights":
        weights[:] = 0  # falls back to uniform weights: tgt is src shifted by 1
    elif case == "identical_points":
        src[:] = 0.3
        tgt[:] = -0.2
    elif case == "collinear":
        src = np.outer(np.linspace(-1, 1, 40), [1.0, 2.0, 3.0]).astype(np.float32)
        tgt = src[:, [1, 0, 2]]
    else:
        weights[1:] = 0
    r, t = rigid.weighted_procrustes(jnp.asarray(src), jnp.asarray(tgt), jnp.asarray(weights))
    r, t = np.asarray(r), np.asarray(t)
    assert np.isfinite(r).all() and np.isfinite(t).all()
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-5)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-5)
    # Whatever the rotation, the weighted centroid lands on the target's.
    w = weights if weights.sum() > 0 else np.ones_like(weights)
    centroid = (w[:, None] * src).sum(0) / w.sum()
    np.testing.assert_allclose(r @ centroid + t, (w[:, None] * tgt).sum(0) / w.sum(), atol=1e-5)
    if case == "zero_weights":
        np.testing.assert_allclose(r, np.eye(3), atol=1e-5)
        np.testing.assert_allclose(t, np.ones(3), atol=1e-5)


def test_procrustes_vmaps_over_a_batch():
    rng = np.random.default_rng(5)
    pairs = [_rigid_pair(rng) for _ in range(4)]
    src = jnp.asarray(np.stack([p[0] for p in pairs]))
    tgt = jnp.asarray(np.stack([p[1] for p in pairs]))
    r, t = jax.jit(jax.vmap(rigid.weighted_procrustes))(src, tgt, jnp.ones(src.shape[:2]))
    np.testing.assert_allclose(np.asarray(r), np.stack([p[2] for p in pairs]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(t), np.stack([p[3] for p in pairs]), atol=1e-6)


def test_compose_and_apply_transform_agree():
    rng = np.random.default_rng(6)
    ra, rb = (jnp.asarray(random_rotation(rng), jnp.float32) for _ in range(2))
    ta, tb = (jnp.asarray(rng.normal(size=3), jnp.float32) for _ in range(2))
    x = jnp.asarray(rng.normal(size=(10, 3)), jnp.float32)
    r, t = rigid.compose(ra, ta, rb, tb)
    np.testing.assert_allclose(
        rigid.apply_transform(r, t, x),
        rigid.apply_transform(ra, ta, rigid.apply_transform(rb, tb, x)),
        atol=1e-5,
    )


def test_rotation_derivative_matches_finite_differences_and_stays_finite():
    rng = np.random.default_rng(7)
    f = rigid.rotation_from_cross_covariance
    for _ in range(5):
        h = jnp.asarray(rng.normal(size=(3, 3)), jnp.float32)
        d = jnp.asarray(rng.normal(size=(3, 3)), jnp.float32)
        jvp = jax.jvp(f, (h,), (d,))[1]
        eps = 1e-3
        fd = (f(h + eps * d) - f(h - eps * d)) / (2 * eps)
        np.testing.assert_allclose(np.asarray(jvp), np.asarray(fd), atol=2e-3)
    # Repeated singular values (identity, planar) differentiate the SVD to NaN; the rotation stays finite.
    for h in (jnp.eye(3), jnp.diag(jnp.array([1.0, 1.0, 0.0])), jnp.zeros((3, 3))):
        grad = jax.grad(lambda m: jnp.sum(f(m) * jnp.arange(9.0).reshape(3, 3)))(h)
        assert np.isfinite(np.asarray(grad)).all()


def test_cube_rotations_are_the_24_proper_turns_of_a_cube_and_cover_every_rotation():
    """``rotation_search`` starts from these: each a proper rotation, the identity first, closed under
    composition (a group), and every rotation within 62.8 degrees of one of them."""
    turns = rigid.cube_rotations()
    assert turns.shape == (24, 3, 3)
    np.testing.assert_array_equal(turns[0], np.eye(3))
    np.testing.assert_allclose(np.einsum("kji,kjl->kil", turns, turns), np.broadcast_to(np.eye(3), turns.shape))
    assert np.allclose(np.linalg.det(turns), 1.0)
    flat = {tuple(t.ravel()) for t in turns}
    assert len(flat) == 24 and all(tuple((a @ b).ravel()) in flat for a in turns for b in turns)
    rng = np.random.default_rng(0)
    nearest = [
        min(rigid.rotation_angle_deg(t.T @ r) for t in turns) for r in (random_rotation(rng) for _ in range(2000))
    ]
    assert max(nearest) <= 62.8 and max(nearest) > 50.0
