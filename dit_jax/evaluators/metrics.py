"""Registration errors. Pure functions of estimates and ground truth, batched over any leading axes.

* :func:`rotation_error_deg`, :func:`translation_error`: isotropic errors (angle of R_gt^T R, |t - t_gt|).
* :func:`matrix_to_euler_zyx`: Euler angles as scipy's ``as_euler('zyx', degrees=True)``, the authors'
  convention (docs/network.md, section 13).
* :func:`summarise`: the authors' table metrics (RMSE and MAE of Euler angles and of translation components),
  isotropic means, RPM-Net's Chamfer distance and success ratios over a sweep of thresholds.
* :func:`surface_error`, :func:`symmetry_tolerance`, :func:`within_up_to_symmetry`: errors that a symmetry of
  the shape cannot tell from the truth (a vase turned about its axis) count as the truth's own.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.geometry.rigid import axis_angle_matrix


@jax.jit
def rotation_error_deg(rotation, rotation_gt):
    """Isotropic rotation error: the angle of ``R_gt^T R`` in degrees. (..., 3, 3) -> (...).

    Jitted (as is :func:`translation_error`): evaluation calls it on host arrays of many sizes, and one
    compiled program per size costs less than compiling each operation on its own."""
    m = jnp.matmul(jnp.swapaxes(rotation_gt, -1, -2), rotation, precision=jax.lax.Precision.HIGHEST)
    # atan2 of sine (from the skew part) and cosine (from the trace): accurate at every angle, where
    # arccos of the trace alone loses about 0.03 degrees to float32 rounding near 0.
    cos = (jnp.trace(m, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = jnp.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    sin = 0.5 * jnp.linalg.norm(skew, axis=-1)
    return jnp.degrees(jnp.arctan2(sin, cos))


@jax.jit
def translation_error(translation, translation_gt):
    """Isotropic translation error ``|t - t_gt|``. (..., 3) -> (...)."""
    return jnp.linalg.norm(translation - translation_gt, axis=-1)


def matrix_to_euler_zyx(rotation) -> np.ndarray:
    """Angles (az, ay, ax) in degrees with ``R = Rx(ax) Ry(ay) Rz(az)``, as scipy's ``as_euler('zyx')``.

    The inverse of :func:`dit_jax.data.pairs.euler_zyx_to_matrix`; ay lies in [-90, 90], az and ax in
    (-180, 180]. (..., 3, 3) -> (..., 3).
    """
    r = np.asarray(rotation, np.float64)
    ay = np.arcsin(np.clip(r[..., 0, 2], -1.0, 1.0))
    az = np.arctan2(-r[..., 0, 1], r[..., 0, 0])
    ax = np.arctan2(-r[..., 1, 2], r[..., 2, 2])
    return np.degrees(np.stack([az, ay, ax], axis=-1))


def chamfer_distance(
    src_moved: np.ndarray, tgt: np.ndarray, src_clean_moved: np.ndarray, tgt_clean: np.ndarray
) -> np.ndarray:
    """RPM-Net's modified Chamfer distance (squared distances).

    ``mean_i min_j |src_moved_i - tgt_clean_j|^2 + mean_j min_i |tgt_j - src_clean_moved_i|^2``: the source
    moved by the estimate against the clean, complete shape in the target frame, and the target against the
    clean complete shape moved by estimate o truth^-1. Noise-free and crop-free, so a perfect estimate scores
    the noise alone. Shapes (B, N, 3), (B, M, 3), (B, P, 3), (B, P, 3) -> (B,).
    """

    def directed(a, b):
        d = np.sum((a[:, :, None, :] - b[:, None, :, :]) ** 2, axis=-1)
        return d.min(axis=2).mean(axis=1)

    return directed(src_moved, tgt_clean) + directed(tgt, src_clean_moved)


def summarise(
    rotation,
    translation,
    rotation_gt,
    translation_gt,
    *,
    rotation_thresholds: Sequence[float] = (0.5, 1, 2, 5, 10, 20, 45),
    translation_thresholds: Sequence[float] = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5),
) -> dict:
    """The authors' table metrics and more, over B pairs: rotations (B, 3, 3), translations (B, 3).

    Returns a dict of floats: ``rot_rmse``, ``rot_mae`` (degrees, over all Euler components as the authors
    compute them, no wrap-around), ``trans_rmse``, ``trans_mae`` (over components), ``rot_iso`` and
    ``trans_iso`` (means of the isotropic errors), ``success`` (fraction with Euler rotation MAE <= 1 degree
    and translation MAE <= 0.01, the paper's criterion), and ``success_curve``: for each pair of thresholds
    ``(r, t)`` in the sweep the fraction with isotropic errors below both.
    """
    euler_err = matrix_to_euler_zyx(rotation) - matrix_to_euler_zyx(rotation_gt)
    trans_err = np.asarray(translation, np.float64) - np.asarray(translation_gt, np.float64)
    rot_iso = np.asarray(rotation_error_deg(jnp.asarray(rotation), jnp.asarray(rotation_gt)))
    trans_iso = np.linalg.norm(trans_err, axis=-1)
    per_pair_rot_mae = np.abs(euler_err).mean(axis=-1)
    per_pair_trans_mae = np.abs(trans_err).mean(axis=-1)
    return {
        "pairs": int(len(trans_err)),
        "rot_rmse": float(np.sqrt(np.mean(euler_err**2))),
        "rot_mae": float(np.mean(np.abs(euler_err))),
        "trans_rmse": float(np.sqrt(np.mean(trans_err**2))),
        "trans_mae": float(np.mean(np.abs(trans_err))),
        "rot_iso": float(np.mean(rot_iso)),
        "trans_iso": float(np.mean(trans_iso)),
        "success": float(np.mean((per_pair_rot_mae <= 1.0) & (per_pair_trans_mae <= 0.01))),
        "success_curve": {
            "rotation_thresholds": list(map(float, rotation_thresholds)),
            "translation_thresholds": list(map(float, translation_thresholds)),
            "ratio": [
                float(np.mean((rot_iso <= r) & (trans_iso <= t)))
                for r, t in zip(rotation_thresholds, translation_thresholds)
            ],
        },
    }


#: Axes the true pose is turned about to set :func:`symmetry_tolerance`.
SYMMETRY_AXES = 32


def _surface_tree(samples: np.ndarray):
    """A k-d tree over a surface's samples (M, 3) and the midpoints between each and its 6 nearest neighbours:
    the samples' spacing, which floors every distance to the surface, shrinks about 2.5 times."""
    from scipy.spatial import cKDTree

    _, neighbours = cKDTree(samples).query(samples, k=min(7, len(samples)))
    neighbours = neighbours.reshape(len(samples), -1)[:, 1:]
    return cKDTree(np.concatenate([samples, 0.5 * (samples[:, None] + samples[neighbours]).reshape(-1, 3)]))


def _place(shape: np.ndarray, rotation, translation) -> np.ndarray:
    return (
        np.einsum("bij,bpj->bpi", np.asarray(rotation, np.float64), shape)
        + np.asarray(translation, np.float64)[:, None]
    )


def surface_error(shape, rotation, translation, rotation_gt, translation_gt) -> np.ndarray:
    """How far the complete shape placed by the estimate lies from the shape placed by the truth: the mean,
    over the shape's points at the estimated pose, of the distance to the nearest point at the true pose
    (ADD-S, Hinterstoisser et al. 2012). A pose that a symmetry of the shape maps onto the truth scores as the
    truth does (the points' spacing aside), whatever its rotation error.

    shape: (B, P, 3), complete and noise-free, in the source frame; rotation, rotation_gt: (B, 3, 3);
    translation, translation_gt: (B, 3). Returns (B,) in the clouds' units (float64).
    """
    shape = np.asarray(shape, np.float64)
    placed, truth = _place(shape, rotation, translation), _place(shape, rotation_gt, translation_gt)
    return np.array([np.mean(_surface_tree(q).query(p)[0]) for p, q in zip(placed, truth)])


def symmetry_tolerance(
    shape, rotation_gt, translation_gt, degrees: float = 5.0, n_axes: int = SYMMETRY_AXES
) -> np.ndarray:
    """The :func:`surface_error` of the true pose turned by ``degrees`` about the shape's centroid, the median
    over ``n_axes`` axes spread evenly over the sphere (a Fibonacci lattice): how close a typical pose
    ``degrees`` off comes. On a shape without symmetry a larger rotation error lies farther; on a shape with
    one, a pose that its symmetry maps near the truth lies as close whatever its angle.

    shape: (B, P, 3) in the source frame; rotation_gt (B, 3, 3), translation_gt (B, 3). Returns (B,).
    """
    k = np.arange(n_axes) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * k / n_axes), np.pi * (1.0 + 5.0**0.5) * k
    axes = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1)
    turns = np.stack([axis_angle_matrix(a, degrees) for a in axes])  # (A, 3, 3)
    shape = np.asarray(shape, np.float64)
    out = np.empty(len(shape))
    for b, placed in enumerate(_place(shape, rotation_gt, translation_gt)):
        centre, tree = placed.mean(axis=0), _surface_tree(placed)
        turned = np.einsum("aij,pj->api", turns, placed - centre) + centre
        out[b] = np.median(np.mean(tree.query(turned)[0], axis=1))
    return out


def within_up_to_symmetry(
    rotation_error, translation_error, surface, tolerance, degrees: float = 5.0, max_translation: float = 0.05
) -> np.ndarray:
    """Whether each estimate is right up to the shape's symmetry: within ``degrees`` (``rotation_error``,
    degrees) and ``max_translation`` (``translation_error``) of the truth, or placing the complete shape at
    least as close to the truth's placement as a typical pose ``degrees`` off (``surface``, its
    :func:`surface_error`, at most ``tolerance``, its :func:`symmetry_tolerance` for ``degrees``). All (B,);
    returns (B,) bool.
    """
    right = (np.asarray(rotation_error) <= degrees) & (np.asarray(translation_error) <= max_translation)
    return right | (np.asarray(surface) <= np.asarray(tolerance))
