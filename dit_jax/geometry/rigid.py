"""Geometry: nearest neighbours, rigid transforms and weighted Procrustes.

All functions act on one cloud (no batch axis); ``jax.vmap`` them for batches. Points are rows: a cloud is
``(N, 3)``. A rigid motion (R, t) maps x to ``R x + t``.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np

#: Added to every squared distance by the authors' nearest-neighbour search (docs/network.md, section 1).
KNN_EPS = 1e-7
#: Added to the weight sum by the authors' Procrustes (docs/network.md, section 8).
PROCRUSTES_EPS = 1e-7

_HIGHEST = jax.lax.Precision.HIGHEST


def pairwise_sq_dist(x: jax.Array, y: jax.Array) -> jax.Array:
    """Squared Euclidean distances ``|x_i - y_j|^2``.

    Args:
      x: (N, D) points.
      y: (M, D) points.

    Returns:
      (N, M) distances, computed from coordinate differences so that they are exact to float rounding even
      for near neighbours and never negative.
    """
    diff = x[:, None, :] - y[None, :, :]
    return jnp.sum(diff * diff, axis=-1)


def knn(points: jax.Array, k: int) -> jax.Array:
    """Indices of the ``k`` nearest neighbours of every point within its own cloud.

    As in the authors' code (docs/network.md, section 1): squared distances plus 1e-7, ascending, so the point itself
    is its own first neighbour. Ties go to the lower index.

    Args:
      points: (N, 3) cloud, N >= k.
      k: neighbours per point.

    Returns:
      (N, k) int32 indices into ``points``, nearest first.
    """
    chex.assert_rank(points, 2)
    if k > points.shape[0]:
        raise ValueError(f"knn needs at least k={k} points, got {points.shape[0]}")
    dist = pairwise_sq_dist(points, points) + KNN_EPS
    _, idx = jax.lax.top_k(-dist, k)
    return idx.astype(jnp.int32)


def nearest_distances(x: jax.Array, y: jax.Array) -> jax.Array:
    """Distance from each point of ``x`` (N, 3) to its nearest point of ``y`` (M, 3). Returns (N,)."""
    return jnp.sqrt(jnp.min(pairwise_sq_dist(x, y), axis=1))


def spacing(points: jax.Array) -> jax.Array:
    """The cloud's sampling scale: the median distance from a point of ``points`` (N, 3), N >= 2, to its
    nearest other point. Returns ()."""
    dist = pairwise_sq_dist(points, points)
    dist = jnp.where(jnp.eye(points.shape[0], dtype=bool), jnp.inf, dist)
    return jnp.median(jnp.sqrt(jnp.min(dist, axis=1)))


def fitness(src: jax.Array, tgt: jax.Array, radius: jax.Array | float) -> jax.Array:
    """The share of ``src`` (N, 3) points with a ``tgt`` (M, 3) point within ``radius``: how much of the
    source a pose lays onto the target (Open3D's ICP "fitness"). Returns () in [0, 1]."""
    return jnp.mean((nearest_distances(src, tgt) < radius).astype(src.dtype))


def alignment_cost(src: jax.Array, tgt: jax.Array, radius: jax.Array | float) -> jax.Array:
    """The mean distance from ``src`` (N, 3) points to their nearest ``tgt`` (M, 3) point, each capped at
    ``radius``, over ``radius``: 0 where every source point lies on a target point, 1 where none is within
    ``radius``. Unlike :func:`fitness` it keeps falling as a good pose gets better. Returns () in [0, 1]."""
    return jnp.mean(jnp.minimum(nearest_distances(src, tgt), radius)) / radius


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """The angle (degrees) of a rotation (3, 3), in NumPy float64, accurate near 0 (atan2 of the skew part
    and the trace, as :func:`dit_jax.evaluators.metrics.rotation_error_deg`)."""
    m = np.asarray(rotation, np.float64)
    sin = 0.5 * np.linalg.norm([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    return float(np.degrees(np.arctan2(sin, (np.trace(m) - 1.0) / 2.0)))


def axis_angle_matrix(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """The rotation (3, 3) float64 by ``angle_deg`` about ``axis`` (3,), any length but zero (Rodrigues)."""
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def cube_rotations() -> np.ndarray:
    """The 24 rotations that map a cube onto itself (3x3 signed permutation matrices of determinant +1), the
    identity first: (24, 3, 3) float64. Every rotation lies within 62.8 degrees of one of them."""
    import itertools

    found = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), order] = signs
            if np.linalg.det(matrix) > 0:
                found.append(matrix)
    return np.stack(found)


def gather_neighbours(features: jax.Array, idx: jax.Array) -> jax.Array:
    """Features of each point's neighbours.

    Args:
      features: (N, C).
      idx: (N, k) neighbour indices.

    Returns:
      (N, k, C) with ``out[i, j] = features[idx[i, j]]``.
    """
    return jnp.take(features, idx, axis=0)


def apply_transform(rotation: jax.Array, translation: jax.Array, points: jax.Array) -> jax.Array:
    """``R x + t`` for every row x of ``points`` (N, 3); rotation (3, 3), translation (3,)."""
    return jnp.einsum("ij,nj->ni", rotation, points, precision=_HIGHEST) + translation


def compose(rot_a: jax.Array, trans_a: jax.Array, rot_b: jax.Array, trans_b: jax.Array):
    """The motion "first b, then a": returns ``(R_a R_b, R_a t_b + t_a)``."""
    rotation = jnp.matmul(rot_a, rot_b, precision=_HIGHEST)
    translation = jnp.matmul(rot_a, trans_b, precision=_HIGHEST) + trans_a
    return rotation, translation


def _compute_dtype(dtype) -> jnp.dtype:
    # float64 where JAX has it enabled (jax_enable_x64), else float32; never silently below the input's.
    return jnp.promote_types(dtype, jax.dtypes.canonicalize_dtype(jnp.float64))


@jax.custom_jvp
def rotation_from_cross_covariance(cross_cov: jax.Array) -> jax.Array:
    """The rotation R (det +1) maximising ``trace(R^T H)`` for a (3, 3) cross-covariance H (Kabsch).

    With H = U diag(s) V^T: R = U D V^T, D = diag(1, 1, sign(det U det V)) so that R is never a reflection.

    The derivative is that of the special polar factor, ``dR = U' W V^T`` with
    ``W_ij = (M_ij - M_ji) / (s'_i + s'_j)``, ``M = U'^T dH V``, ``U' = U D``, ``s' = D s``. Unlike
    differentiating the SVD itself it is finite when singular values repeat (symmetric or planar shapes);
    where ``s'_i + s'_j`` vanishes R is not differentiable and that term is set to zero.
    """
    return _special_polar(cross_cov)[0]


def _special_polar(cross_cov):
    u, s, vt = jnp.linalg.svd(cross_cov)
    reflect = jnp.linalg.det(u) * jnp.linalg.det(vt) < 0
    signs = jnp.ones(3, cross_cov.dtype).at[2].set(jnp.where(reflect, -1.0, 1.0))
    u_signed = u * signs
    return jnp.matmul(u_signed, vt, precision=_HIGHEST), u_signed, s * signs, vt


@rotation_from_cross_covariance.defjvp
def _rotation_jvp(primals, tangents):
    (cross_cov,), (d_cross_cov,) = primals, tangents
    rotation, u_signed, s_signed, vt = _special_polar(cross_cov)
    mul = lambda a, b: jnp.matmul(a, b, precision=_HIGHEST)
    m = mul(mul(u_signed.T, d_cross_cov), vt.T)
    denom = s_signed[:, None] + s_signed[None, :]
    scale = jnp.maximum(jnp.max(jnp.abs(s_signed)), jnp.finfo(cross_cov.dtype).tiny)
    safe = jnp.abs(denom) > 1e-6 * scale
    w = jnp.where(safe, (m - m.T) / jnp.where(safe, denom, 1.0), 0.0)
    return rotation, mul(mul(u_signed, w), vt)


def weighted_procrustes(src: jax.Array, tgt: jax.Array, weights: jax.Array):
    """The rigid motion that best maps weighted ``src`` onto ``tgt`` (Kabsch, reflection-safe).

    Minimises ``sum_i w_i |R src_i + t - tgt_i|^2`` over rotations R (det +1) and translations t, as in
    docs/network.md, section 8: weights normalised by ``sum |w| + 1e-7``, cross-covariance of the centred
    clouds, SVD, and a sign flip of the last singular direction when the SVD would give a reflection.

    Computed in float64 when ``jax_enable_x64`` is on (like the authors), otherwise in float32 with
    highest-precision matmuls and centred (two-pass) moments, which keeps R within about 1e-6 of float64.

    Degenerate input never yields NaN: with all weights zero the weights become uniform (the authors' code
    would return a meaningless R there); with fewer than three distinct weighted points the rotation is one of
    the minimisers (the SVD's choice) and t still maps the weighted centroid exactly.

    Args:
      src: (N, 3) source points.
      tgt: (N, 3) target points, ``tgt[i]`` matched to ``src[i]``.
      weights: (N,) non-negative weights.

    Returns:
      rotation (3, 3) and translation (3,) in the dtype of ``src``.
    """
    chex.assert_rank([src, tgt, weights], [2, 2, 1])
    chex.assert_equal_shape_prefix([src, tgt, weights], 1)
    out_dtype = src.dtype
    dtype = _compute_dtype(jnp.result_type(src, tgt, weights))
    src, tgt, weights = (a.astype(dtype) for a in (src, tgt, weights))

    weight_sum = jnp.sum(jnp.abs(weights))
    weights = jnp.where(weight_sum > 0, weights, jnp.ones_like(weights))
    weights = weights / (jnp.sum(jnp.abs(weights)) + PROCRUSTES_EPS)

    src_mean = jnp.matmul(weights, src, precision=_HIGHEST)
    tgt_mean = jnp.matmul(weights, tgt, precision=_HIGHEST)
    src_c = src - src_mean
    tgt_c = tgt - tgt_mean
    cross_cov = jnp.einsum("n,ni,nj->ij", weights, tgt_c, src_c, precision=_HIGHEST)

    rotation = rotation_from_cross_covariance(cross_cov)
    translation = tgt_mean - jnp.matmul(rotation, src_mean, precision=_HIGHEST)
    return rotation.astype(out_dtype), translation.astype(out_dtype)
