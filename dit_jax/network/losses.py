"""The paper's training objective (paper section 3.5; docs/network.md, section 11).

Per iteration i, weighted by ``discount ** i``:

* transformation: ``MSE(R^T R_gt, I) + MSE(t, t_gt)`` for the composed estimate;
* cycle consistency (x 0.1): ``MSE(R_ab R_ba, I) + MSE(t_ab, -t_ba)`` for the iteration's own estimates;
* discrimination (x 0.5): ``BCE(w_i, c_i)``, w_i the soft weight of source point i and c_i = 1 where its
  predicted match lies within 0.04 of its true position ``R_gt x_i + t_gt``.

Not the authors': an optional correspondence term (``correspondence_weight``, default 0) that pulls each source
point's soft match ``(P Y)_i`` onto its true position, for the points whose true position has a target point
nearby. The authors' terms supervise the matches only through the pose (and the weights through the
discrimination labels); between clouds that share no point the network alone did not learn from them in the
budget tried (docs/training.md, "Training on clouds that share no point"), nor, in 400 steps, with this term
(docs/training.md).

All functions act on one pair; ``jax.vmap`` them over a batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dit_jax.geometry import rigid
from dit_jax.network.model import Iterations

# Products of 3 x 3 rotations and of coordinates: float32 whatever JAX's default matmul precision is.
_HIGHEST = jax.lax.Precision.HIGHEST

DISCOUNT = 0.9
CYCLE_WEIGHT = 0.1
DISCRIMINATION_WEIGHT = 0.5
MATCH_RADIUS = 0.04
_BCE_EPS = 1e-7


def transformation_loss(rotation, translation, rotation_gt, translation_gt) -> jax.Array:
    """``MSE(R^T R_gt, I) + MSE(t, t_gt)``: rotation (3, 3), translation (3,)."""
    eye = jnp.eye(3, dtype=rotation.dtype)
    rotation_gap = jnp.mean((jnp.matmul(rotation.T, rotation_gt, precision=_HIGHEST) - eye) ** 2)
    return rotation_gap + jnp.mean((translation - translation_gt) ** 2)


def cycle_loss(rotation_ab, translation_ab, rotation_ba, translation_ba) -> jax.Array:
    """``MSE(R_ab R_ba, I) + MSE(t_ab, -t_ba)``, the authors' form of cycle consistency."""
    eye = jnp.eye(3, dtype=rotation_ab.dtype)
    rotation_gap = jnp.mean((jnp.matmul(rotation_ab, rotation_ba, precision=_HIGHEST) - eye) ** 2)
    return rotation_gap + jnp.mean((translation_ab + translation_ba) ** 2)


def match_labels(src, tgt, matches, rotation_gt, translation_gt, radius: float = MATCH_RADIUS) -> jax.Array:
    """c_i: 1.0 where source point i's predicted match ``tgt[matches[i]]`` lies within ``radius`` of its true
    position, else 0.0. src (N, 3) as given (not moved), tgt (M, 3), matches (N,). Returns (N,)."""
    truth = jnp.matmul(src, rotation_gt.T, precision=_HIGHEST) + translation_gt
    distance = jnp.linalg.norm(tgt[matches] - truth, axis=-1)
    return (distance < radius).astype(src.dtype)


def discrimination_loss(weights, labels) -> jax.Array:
    """Mean binary cross-entropy of the soft weights (N,) against the match labels (N,)."""
    w = jnp.clip(weights, _BCE_EPS, 1.0 - _BCE_EPS)
    return -jnp.mean(labels * jnp.log(w) + (1.0 - labels) * jnp.log1p(-w))


def correspondence_loss(soft_targets, src, tgt, rotation_gt, translation_gt, radius: float = MATCH_RADIUS):
    """Mean squared distance from each source point's soft match to its true position, over the points whose
    true position has a target point within ``radius`` (the others have no counterpart to find: cropped away,
    or a sparse region). soft_targets (N, 3), src (N, 3) as given, tgt (M, 3). Returns a scalar (0 where no
    point has a counterpart)."""
    truth = jnp.matmul(src, rotation_gt.T, precision=_HIGHEST) + translation_gt
    nearest = jnp.min(rigid.pairwise_sq_dist(truth, tgt), axis=-1)
    has_counterpart = jax.lax.stop_gradient((nearest < radius**2).astype(src.dtype))
    gaps = jnp.sum((soft_targets - truth) ** 2, axis=-1)
    return jnp.sum(has_counterpart * gaps) / jnp.maximum(jnp.sum(has_counterpart), 1.0)


def dit_loss(
    its: Iterations,
    src,
    tgt,
    rotation_gt,
    translation_gt,
    discount: float = DISCOUNT,
    match_radius: float = MATCH_RADIUS,
    correspondence_weight: float = 0.0,
):
    """The total loss of one pair and its terms (each summed over iterations with the discount).

    Args:
      its: :func:`dit_jax.network.model.unroll`'s output for the pair.
      src: (N, 3), tgt (M, 3): the input clouds.
      rotation_gt: (3, 3), translation_gt (3,): the true source-to-target motion.
      match_radius: the discrimination labels' radius (the authors' 0.04; clouds sampled independently have
        their nearest true counterpart about 0.04 away at 512 points, so they need a wider one).
      correspondence_weight: the weight of :func:`correspondence_loss` (its radius ``match_radius``); 0, the
        authors' objective, leaves it out.

    Returns:
      ``(total, terms)``, terms a dict with ``transformation``, ``cycle``, ``discrimination`` (unweighted by
      their factors), ``correspondence`` where its weight is not 0, and ``match_accuracy`` (fraction of
      last-iteration matches within the radius).
    """
    n_iters = its.rotation.shape[0]
    factors = discount ** jnp.arange(n_iters, dtype=src.dtype)
    trans = jax.vmap(transformation_loss, (0, 0, None, None))(
        its.rotation, its.translation, rotation_gt, translation_gt
    )
    cycle = jax.vmap(cycle_loss)(its.rotation_ab, its.translation_ab, its.rotation_ba, its.translation_ba)
    labels = jax.vmap(match_labels, (None, None, 0, None, None, None))(
        src, tgt, its.correspondences, rotation_gt, translation_gt, match_radius
    )
    disc = jax.vmap(discrimination_loss)(its.soft_weights, jax.lax.stop_gradient(labels))
    terms = {
        "transformation": jnp.sum(factors * trans),
        "cycle": jnp.sum(factors * cycle),
        "discrimination": jnp.sum(factors * disc),
        "match_accuracy": jnp.mean(labels[-1]),
    }
    total = terms["transformation"] + CYCLE_WEIGHT * terms["cycle"] + DISCRIMINATION_WEIGHT * terms["discrimination"]
    if correspondence_weight:
        corr = jax.vmap(correspondence_loss, (0, None, None, None, None, None))(
            its.soft_targets, src, tgt, rotation_gt, translation_gt, match_radius
        )
        terms["correspondence"] = jnp.sum(factors * corr)
        total = total + correspondence_weight * terms["correspondence"]
    return total, terms
