"""GMCCE: geometric-matching correspondence confidence (paper section 3.4, Algorithm 1; docs/network.md, section 9).

A correspondence x_i -> y_i is trusted when the triangles x_i forms with its neighbours keep their side
lengths in the target: rigid motions preserve them, wrong matches do not. Acts on one pair of clouds.
"""

from __future__ import annotations

import itertools
import math

import chex
import jax
import jax.numpy as jnp

from dit_jax.geometry import rigid

#: Added to the target's squared side lengths (docs/network.md, section 9 step 3).
SIDE_EPS = 1e-6
#: Inside the square root of the triangle errors (step 5).
ERROR_EPS = 1e-6


def triangle_neighbours(src: jax.Array, k: int, min_dist2: float) -> jax.Array:
    """The ``k`` triangle partners of every source point.

    Candidates are the points at squared distance (plus 1e-7) at least ``min_dist2``, nearest first, as the
    authors choose them. Where a point has fewer than ``k`` candidates the authors' top-k fills up with
    arbitrary near points; here the rest is filled with the excluded points farthest first, so that the
    point itself comes last and a vertex repeats only when the cloud has at most ``k`` points.

    Args:
      src: (N, 3) source points.
      k: partners per point (k_s).
      min_dist2: squared distance below which a point is no candidate.

    Returns:
      (N, k) int32 indices into ``src``.
    """
    dist = rigid.pairwise_sq_dist(src, src) + rigid.KNN_EPS
    candidate = dist >= min_dist2
    # Excluded points sort after every candidate, farthest first.
    beyond = jnp.max(dist) + 1.0
    key = jnp.where(candidate, dist, beyond + (min_dist2 - dist))
    _, idx = jax.lax.top_k(-key, min(k, src.shape[0]))
    return idx.astype(jnp.int32)


def _pairs(k: int) -> jax.Array:
    return jnp.asarray(list(itertools.combinations(range(k), 2)), dtype=jnp.int32).reshape(-1, 2)


def triangle_sides(points: jax.Array, partners: jax.Array) -> jax.Array:
    """Sorted squared side lengths of every triangle (p_i, p_a, p_b) over pairs a < b of partners.

    Args:
      points: (N, 3).
      partners: (N, k) partner indices per point.

    Returns:
      (N, k (k - 1) / 2, 3) squared side lengths, ascending per triangle, pairs in
      ``itertools.combinations`` order. These are the triangulated descriptor of the paper.
    """
    pairs = _pairs(partners.shape[1])
    p0 = points[:, None, :]
    p1 = points[partners[:, pairs[:, 0]]]
    p2 = points[partners[:, pairs[:, 1]]]
    sq = lambda d: jnp.sum(d * d, axis=-1)
    sides = jnp.stack([sq(p0 - p1), sq(p1 - p2), sq(p0 - p2)], axis=-1)
    return jnp.sort(sides, axis=-1)


def matching_error(src: jax.Array, tgt: jax.Array, partners: jax.Array) -> jax.Array:
    """E_i: how much the triangles around each correspondence change shape (0 for a rigid motion).

    Per triangle ``e = sum (l_src - l_tgt)^2 / sum (l_src + l_tgt)^2`` over the three sorted squared sides
    (target sides + 1e-6); E_i is the mean of ``sqrt(e + 1e-6)`` over the k smallest of point i's triangles.

    Args:
      src: (N, 3) source points.
      tgt: (N, 3) their correspondences (the authors use the soft targets P Y).
      partners: (N, k) from :func:`triangle_neighbours`.

    Returns:
      (N,) errors.
    """
    l_src = triangle_sides(src, partners)
    l_tgt = triangle_sides(tgt, partners) + SIDE_EPS
    err = jnp.sum((l_src - l_tgt) ** 2, axis=-1) / jnp.sum((l_src + l_tgt) ** 2, axis=-1)
    n_keep = min(partners.shape[1], err.shape[1])
    smallest = -jax.lax.top_k(-err, n_keep)[0]
    return jnp.mean(jnp.sqrt(smallest + ERROR_EPS), axis=-1)


def confidence(
    src: jax.Array, tgt: jax.Array, *, k: int = 10, sharpness: float = 30.0, min_dist2: float = 0.1
) -> jax.Array:
    """c_i = 2 sigmoid(-lambda (E_i - min_j E_j)), in (0, 1]; 1 for the best-kept correspondence.

    Args:
      src: (N, 3) source points, N >= 3.
      tgt: (N, 3) corresponding target points.
      k: k_s, triangle partners per point.
      sharpness: lambda.
      min_dist2: see :func:`triangle_neighbours`.

    Returns:
      (N,) confidences.
    """
    chex.assert_rank([src, tgt], 2)
    chex.assert_equal_shape([src, tgt])
    partners = triangle_neighbours(src, k, min_dist2)
    error = matching_error(src, tgt, partners)
    # The paper does not subtract the minimum; the authors' code (and their thresholds) do.
    error = error - jnp.min(error)
    return 2.0 * jax.nn.sigmoid(-sharpness * error)


def weights(
    src: jax.Array,
    tgt: jax.Array,
    *,
    k: int = 10,
    sharpness: float = 30.0,
    threshold: float | jax.Array = 0.99,
    min_dist2: float = 0.1,
    min_keep: float = 0.0,
) -> jax.Array:
    """GMCCE's inlier weights: 1.0 where :func:`confidence` exceeds ``threshold``, else 0.0. Shape (N,).

    ``min_keep`` > 0 also keeps the ``ceil(min_keep N)`` most confident correspondences, however low their
    confidence: where no triangle keeps its sides exactly (clouds sampled independently, noise), the
    authors' fixed threshold can keep a handful of matches, too few for a pose; ranking by confidence still
    holds there. 0 is the authors' rule.
    """
    conf = confidence(src, tgt, k=k, sharpness=sharpness, min_dist2=min_dist2)
    inliers = conf > threshold
    if min_keep > 0:
        n_keep = min(src.shape[0], max(1, math.ceil(min_keep * src.shape[0])))
        kth = jax.lax.top_k(conf, n_keep)[0][-1]
        inliers = inliers | (conf >= kth)
    return inliers.astype(src.dtype)
