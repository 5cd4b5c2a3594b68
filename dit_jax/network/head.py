"""The head: feature similarity, correspondences, their weights and the pose (docs/network.md, sections 6-8).

Two modes, as in the authors' code:

* soft (training, and the first inference iteration): ``P = softmax(temperature S)`` row-wise; each source
  point takes its most similar target point, weighted by that probability.
* GMCCE (later inference iterations): ``P = softmax(10000 S)``; the weights are GMCCE's 0/1 inlier flags,
  computed on the soft targets ``P Y``.

Both end in weighted Procrustes on the hard matches. Everything acts on one pair of clouds.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import linen as nn

from dit_jax.geometry import rigid
from dit_jax.network import gmcce
from dit_jax.network.configs import DITConfig
from dit_jax.network.layers import clip_inward, einsum, layer_norm, torch_dense

#: The inverse temperature of the GMCCE mode's near-hard softmax.
GMCCE_SOFTMAX_SCALE = 10000.0


class TemperatureNet(nn.Module):
    """The learned softmax temperature from the gap between the two clouds' mean features.

    r = |mean(Phi_X) - mean(Phi_Y)|; three blocks of Linear, LayerNorm, LeakyReLU(0.01); Linear to one value,
    LeakyReLU; clamped to [1 / factor, factor].

    The clamp's value is the authors'; its gradient is not (:func:`dit_jax.network.layers.clip_inward`). With their
    clamp a temperature below 1 / factor gets no gradient at all, and a freshly initialised net starts there
    whenever its last LeakyReLU is negative, which happens for many seeds. The soft correspondences then stay uniform (weights 1 / M), and training
    wrecked the matching until the temperature drifted out by chance, or for good (docs/training.md,
    "Training that learns on every seed").
    """

    hidden: int = 128
    factor: float = 100.0
    precision: str = "highest"  # of the products, see dit_jax.network.layers.dot_precision

    @nn.compact
    def __call__(self, phi_x: jax.Array, phi_y: jax.Array) -> jax.Array:
        """phi_x: (N, E), phi_y: (M, E) -> scalar temperature."""
        x = jnp.abs(jnp.mean(phi_x, axis=0) - jnp.mean(phi_y, axis=0))
        for i in (0, 3, 6):  # the authors' Sequential indices: Linear at i, LayerNorm at i + 1
            x = torch_dense(self.hidden, f"fc{i}", precision=self.precision)(x)
            x = jax.nn.leaky_relu(layer_norm(f"norm{i + 1}")(x), negative_slope=0.01)
        x = jax.nn.leaky_relu(torch_dense(1, "fc9", precision=self.precision)(x), negative_slope=0.01)
        return clip_inward(x[0], 1.0 / self.factor, self.factor)


def similarity(phi_x: jax.Array, phi_y: jax.Array, precision: str = "highest") -> jax.Array:
    """S = Phi_X Phi_Y^T / sqrt(E): (N, E), (M, E) -> (N, M). ``precision``: see
    :func:`dit_jax.network.layers.dot_precision`."""
    scale = jnp.sqrt(jnp.asarray(phi_x.shape[-1], phi_x.dtype))
    return einsum("ne,me->nm", phi_x, phi_y, precision=precision) / scale


class HeadOutput(NamedTuple):
    """The head's result for one direction. N source points."""

    rotation: jax.Array  # (3, 3)
    translation: jax.Array  # (3,)
    correspondences: jax.Array  # (N,) int32, index of each source point's match in the target
    weights: jax.Array  # (N,) the Procrustes weights actually used
    soft_weights: jax.Array  # (N,) max_j softmax(temperature S)_ij, the discrimination loss's input
    gmcce_fallback: jax.Array  # () bool, True where GMCCE rejected every match and soft weights were used
    tgt_soft: jax.Array  # (N, 3) P Y, the soft targets GMCCE scores (the soft mode's in soft mode)


def head(
    src: jax.Array,
    tgt: jax.Array,
    scores: jax.Array,
    temperature: jax.Array,
    config: DITConfig,
    use_gmcce: bool,
    gmcce_threshold: jax.Array | None = None,
) -> HeadOutput:
    """Correspondences, weights and the rigid motion mapping ``src`` onto ``tgt``.

    Args:
      src: (N, 3) source points.
      tgt: (M, 3) target points.
      scores: (N, M) similarity S from :func:`similarity`.
      temperature: scalar from :class:`TemperatureNet`.
      config: supplies the GMCCE parameters.
      use_gmcce: GMCCE mode (static).
      gmcce_threshold: () GMCCE's threshold as an array, in place of ``config.gmcce_threshold``: one compiled
        program for several thresholds.

    Returns:
      A :class:`HeadOutput`. When GMCCE flags no correspondence as an inlier (possible only with
      ``gmcce_threshold >= 1`` or non-finite features) the soft-mode weights are used and ``gmcce_fallback``
      is set, so the pose stays defined.
    """
    soft_probs = jax.nn.softmax(temperature * scores, axis=-1)
    soft_weights = jnp.max(soft_probs, axis=-1)
    if use_gmcce:
        probs = jax.nn.softmax(GMCCE_SOFTMAX_SCALE * scores, axis=-1)
    else:
        probs = soft_probs
    correspondences = jnp.argmax(probs, axis=-1).astype(jnp.int32)
    tgt_soft = jnp.matmul(probs, tgt, precision=jax.lax.Precision.HIGHEST)
    if use_gmcce:
        inliers = gmcce.weights(
            src,
            tgt_soft,
            k=config.gmcce_k,
            sharpness=config.gmcce_sharpness,
            threshold=config.gmcce_threshold if gmcce_threshold is None else gmcce_threshold,
            min_dist2=config.gmcce_min_dist2,
            min_keep=config.gmcce_min_keep,
        )
        fallback = jnp.sum(inliers) == 0
        weights = jnp.where(fallback, soft_weights, inliers)
    else:
        fallback = jnp.asarray(False)
        weights = soft_weights
    rotation, translation = rigid.weighted_procrustes(src, tgt[correspondences], weights)
    return HeadOutput(rotation, translation, correspondences, weights, soft_weights, fallback, tgt_soft)
