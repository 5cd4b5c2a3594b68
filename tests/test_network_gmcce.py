import jax
import jax.numpy as jnp
import numpy as np
from conftest import random_rotation

from dit_jax.network import gmcce

#: GMCCE's weights as the registration's program computes them, jitted: one compiled program for the
#: ModelNet shapes' size, where op-by-op dispatch compiles each operation.
_weights = jax.jit(gmcce.weights, static_argnames=("k", "sharpness", "min_dist2", "min_keep"))


def _moved(shape, seed):
    rng = np.random.default_rng(seed)
    rot = random_rotation(rng)
    return (shape @ rot.T + rng.uniform(-0.5, 0.5, 3)).astype(np.float32), rng


def test_exact_correspondences_on_modelnet_get_weight_one(modelnet_shapes):
    for index in range(5):
        src = modelnet_shapes[index]
        tgt, _ = _moved(src, index)
        w = np.asarray(_weights(jnp.asarray(src), jnp.asarray(tgt), threshold=0.99))
        assert (w == 1.0).all(), f"shape {index}: {int((w == 0).sum())} exact matches rejected"


def test_scrambled_correspondences_on_modelnet_mostly_get_weight_zero(modelnet_shapes):
    for index in range(5):
        src = modelnet_shapes[index]
        tgt, rng = _moved(src, index)
        tgt = tgt[rng.permutation(len(tgt))]
        w = np.asarray(_weights(jnp.asarray(src), jnp.asarray(tgt), threshold=0.6))
        assert w.mean() < 0.05, f"shape {index}: {w.mean():.1%} of scrambled matches kept"


def test_confidence_separates_inliers_from_outliers(modelnet_shapes):
    src = modelnet_shapes[7]
    tgt, rng = _moved(src, 7)
    outliers = rng.choice(len(src), 300, replace=False)
    tgt[outliers] = tgt[rng.permutation(outliers)]
    w = np.asarray(_weights(jnp.asarray(src), jnp.asarray(tgt), threshold=0.9))
    inliers = np.setdiff1d(np.arange(len(src)), outliers)
    assert w[inliers].mean() > 0.9 and w[outliers].mean() < 0.1


def test_triangle_sides_are_sorted_squared_lengths():
    points = jnp.array([[0.0, 0, 0], [3, 0, 0], [0, 4, 0]])
    sides = gmcce.triangle_sides(points, jnp.array([[1, 2], [0, 2], [0, 1]]))
    np.testing.assert_allclose(np.asarray(sides[0, 0]), [9.0, 16.0, 25.0])


def test_triangle_neighbours_skip_near_points_then_fill_farthest_first():
    # Point 0's candidates are the points at squared distance >= 0.1: 3 and 4 (nearest first). With k=4 the
    # rest are the excluded ones, farthest first, so point 0 itself comes last.
    points = jnp.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    idx = np.asarray(gmcce.triangle_neighbours(points, 4, 0.1))
    np.testing.assert_array_equal(idx[0], [3, 4, 2, 1])
    idx5 = np.asarray(gmcce.triangle_neighbours(points, 5, 0.1))
    np.testing.assert_array_equal(idx5[0], [3, 4, 2, 1, 0])


def test_degenerate_clouds_give_finite_weights():
    rng = np.random.default_rng(0)
    line = np.outer(np.linspace(0, 1, 64), [1.0, 0.5, 0.0]).astype(np.float32)
    for src, tgt in [
        (np.zeros((64, 3), np.float32), np.zeros((64, 3), np.float32)),  # every point identical
        (line, line[::-1].copy()),  # collinear
        (rng.normal(size=(12, 3)).astype(np.float32), rng.normal(size=(12, 3)).astype(np.float32)),  # few
    ]:
        conf = np.asarray(gmcce.confidence(jnp.asarray(src), jnp.asarray(tgt)))
        assert np.isfinite(conf).all() and conf.max() == 1.0


def test_min_keep_keeps_the_most_confident_share(modelnet_shapes):
    """Where noise leaves no triangle exact, the fixed threshold keeps almost nothing; ``min_keep`` keeps the
    most confident share, and those are mostly the true matches."""
    src = modelnet_shapes[3]
    tgt, rng = _moved(src, 3)
    tgt = tgt + rng.normal(0, 0.02, tgt.shape).astype(np.float32)
    outliers = rng.choice(len(src), 400, replace=False)
    tgt[outliers] = tgt[rng.permutation(outliers)]
    strict = np.asarray(_weights(jnp.asarray(src), jnp.asarray(tgt), threshold=0.99))
    kept = np.asarray(_weights(jnp.asarray(src), jnp.asarray(tgt), threshold=0.99, min_keep=0.2))
    assert strict.sum() < 0.05 * len(src)
    assert kept.sum() >= np.ceil(0.2 * len(src)) and kept.sum() < 0.25 * len(src)
    assert (kept >= strict).all(), "never fewer than the threshold keeps"
    assert kept[outliers].sum() < 0.15 * kept.sum()
