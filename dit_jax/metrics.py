"""Registration errors. Pure functions of one estimate; ``jax.vmap`` or numpy-broadcast them over batches."""

from __future__ import annotations

import jax.numpy as jnp


def rotation_error_deg(rotation, rotation_gt):
    """Isotropic rotation error: the angle of ``R_gt^T R`` in degrees. (..., 3, 3) -> (...)."""
    relative = jnp.swapaxes(rotation_gt, -1, -2) @ rotation
    cos = (jnp.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0
    return jnp.degrees(jnp.arccos(jnp.clip(cos, -1.0, 1.0)))


def translation_error(translation, translation_gt):
    """Isotropic translation error ``|t - t_gt|``. (..., 3) -> (...)."""
    return jnp.linalg.norm(translation - translation_gt, axis=-1)
