"""Stage 1 of the pipeline: each cloud checked, resampled by farthest-point sampling to the settings' point count,
and both moved into the unit sphere with one shared scale (:func:`sample_and_normalise`), once
:func:`check_pair` has checked them."""

from __future__ import annotations

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.pipeline.settings import FAR_APART, InferenceSettings

#: Stage 1 warns (:class:`SizeMismatchWarning`) where one cloud's radius is this many times the other's: two
#: views of one object differ far less, millimetres and metres 1000 times, and a rigid motion cannot rescale.
SIZE_RATIO_WARNING = 10.0


class InputError(ValueError):
    """A cloud that DIT cannot register; the message names it."""


class SizeMismatchWarning(UserWarning):
    """The two clouds differ in size far more than views of one object do: most likely different units."""


#: Coordinates the pipeline takes: squared lengths of larger ones overflow float64 (near 1e154), of clouds
#: smaller across than this they underflow.
LARGEST = 1e100
SMALLEST = 1e-100


def _points(count: int) -> str:
    return f"{count:,} point" + ("" if count == 1 else "s")


def check_cloud(name: str, points, min_points: int) -> np.ndarray:
    """Returns ``points`` as (N, 3) float64 or raises :class:`InputError` saying what is wrong with it."""
    try:
        array = np.asarray(points)
    except (TypeError, ValueError) as err:
        raise InputError(f"{name}: not an array of coordinates ({err})") from None
    if array.ndim != 2 or array.shape[1] != 3:
        raise InputError(f"{name}: expected N x 3 coordinates, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InputError(f"{name}: expected real coordinates, got dtype {array.dtype}")
    array = array.astype(np.float64, copy=False)
    bad = ~np.isfinite(array).all(axis=1)
    if bad.any():
        raise InputError(f"{name}: {int(bad.sum())} of {len(array)} points have NaN or Inf coordinates")
    if len(array) < min_points:
        raise InputError(f"{name}: {_points(len(array))}; the model needs at least {min_points}")
    extent = float(np.ptp(array, axis=0).max())
    largest = float(np.abs(array).max())
    # Same point up to rounding: relative to the coordinates' own size, so a cloud in any unit passes.
    if extent <= 1e-9 * largest:
        raise InputError(f"{name}: all {_points(len(array))} are the same point")
    if largest > LARGEST or extent < SMALLEST:
        raise InputError(
            f"{name}: coordinates up to {largest:.3g} across {extent:.3g}; squared lengths of such a cloud leave "
            f"float64's range: rescale it (any unit between {SMALLEST:g} and {LARGEST:g} works)"
        )
    # A line leaves the rotation about itself undetermined, whatever the other cloud. Its spread across the
    # line is zero up to rounding; a millionth of the spread along it is a line in float32, the network's type.
    centred = (array - array.mean(axis=0)) / extent  # scale-free: the check reads the same in any unit
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred), 0.0))  # ascending
    if spread[1] <= 1e-6 * spread[2]:
        raise InputError(
            f"{name}: its {_points(len(array))} lie on one line, so no rotation about that line can be told from another"
        )
    return array


def farthest_point_sample(points: np.ndarray, n: int, *, seed: int = 0, pool: int | None = None) -> np.ndarray:
    """Indices of ``n`` points spread over the cloud by farthest-point sampling.

    Each point taken is the one farthest from all taken before (ties: the lowest index), starting from a
    seeded random point, in one jitted loop (:func:`_farthest_points`) in float32.

    Args:
      points: (N, 3).
      n: how many to take; all N (in order) when N <= n.
      seed: picks the first point (and the random thinning).
      pool: above this many points the cloud is first thinned uniformly at random to ``pool`` points.

    Returns:
      (min(N, n),) int64 indices into ``points``, no repeats.
    """
    count = len(points)
    if count <= n:
        return np.arange(count)
    rng = np.random.default_rng(seed)
    candidates = np.sort(rng.choice(count, pool, replace=False)) if pool and count > pool else np.arange(count)
    cloud = np.asarray(points[candidates], np.float64)
    first = int(rng.integers(len(cloud)))
    # Centred before float32, so that squared distances keep their digits far from the origin. Padded to one
    # of a few sizes per power of two (at most 1/8 more), so clouds of similar size share one compilation.
    cloud = (cloud - cloud.mean(axis=0)).astype(np.float32)
    step = 1 << max(len(cloud).bit_length() - 4, 0)
    padded = np.zeros((3, -(-len(cloud) // step) * step), np.float32)
    padded[:, : len(cloud)] = cloud.T
    chosen = _farthest_points(padded, np.int32(len(cloud)), np.int32(first), n)
    return candidates[np.asarray(chosen, np.int64)]


@functools.partial(jax.jit, static_argnames=("n",))
def _farthest_points(xyz: jax.Array, count: jax.Array, first: jax.Array, n: int) -> jax.Array:
    """Farthest-point sampling of the first ``count`` columns of ``xyz`` (3, P), from column ``first``.

    Coordinates as three rows and the arg-max as a max then a min over indices: XLA's CPU backend vectorises
    both, where a (P, 3) layout and ``jnp.argmax`` (one reduction of value-index pairs) run several times
    slower. Padding columns start at distance -1 and are never taken. Returns (n,) int32.
    """
    x, y, z = xyz
    index = jnp.arange(x.shape[0], dtype=jnp.int32)

    def distances(i):
        return (x - x[i]) ** 2 + (y - y[i]) ** 2 + (z - z[i]) ** 2

    def body(i, state):
        chosen, nearest = state
        farthest = jnp.min(jnp.where(nearest == jnp.max(nearest), index, x.shape[0]))
        return chosen.at[i].set(farthest), jnp.minimum(nearest, distances(farthest))

    nearest = jnp.where(index < count, distances(first), -1.0)
    chosen = jnp.zeros(n, jnp.int32).at[0].set(first)
    return jax.lax.fori_loop(1, n, body, (chosen, nearest))[0]


def normalise(src: np.ndarray, tgt: np.ndarray, centring: str = "shared"):
    """Centres (per ``centring``, see :class:`dit_jax.pipeline.settings.InferenceSettings`) and scales two clouds into the unit sphere
    with one shared scale, the largest distance of a point from its centre. src (N, 3), tgt (M, 3).

    Returns ``(src_n, tgt_n, src_centre (3,), tgt_centre (3,), scale)``, float64."""
    src_centre, tgt_centre = src.mean(axis=0), tgt.mean(axis=0)
    if centring == "auto":
        radius = max(
            float(np.linalg.norm(c - centre, axis=1).max()) for c, centre in ((src, src_centre), (tgt, tgt_centre))
        )
        centring = "separate" if np.linalg.norm(src_centre - tgt_centre) > FAR_APART * radius else "shared"
    if centring == "shared":
        src_centre = tgt_centre = np.concatenate([src, tgt]).mean(axis=0)
    scale = max(
        float(np.linalg.norm(src - src_centre, axis=1).max()), float(np.linalg.norm(tgt - tgt_centre, axis=1).max())
    )
    return (src - src_centre) / scale, (tgt - tgt_centre) / scale, src_centre, tgt_centre, scale


def to_caller_units(
    rotation: np.ndarray, translation: np.ndarray, src_centre: np.ndarray, tgt_centre: np.ndarray, scale: float
) -> np.ndarray:
    """The translation of a motion found between normalised clouds, in the caller's frame:
    ``s t' + c_y - R c_x``."""
    return scale * translation + tgt_centre - rotation @ src_centre


@dataclasses.dataclass(frozen=True)
class Normalised:
    """Stage 1's output for one pair: the caller's clouds (float64), the rows sampled from each, the sampled
    clouds in the unit sphere (float32) and the centres and scale that map motions back."""

    src: np.ndarray
    tgt: np.ndarray
    src_indices: np.ndarray
    tgt_indices: np.ndarray
    src_n: np.ndarray
    tgt_n: np.ndarray
    src_centre: np.ndarray
    tgt_centre: np.ndarray
    scale: float


def check_pair(src, tgt, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """src (N, 3), tgt (M, 3) in any units, checked (:func:`check_cloud`) and as float64 arrays; raises
    :class:`InputError` on a cloud DIT cannot register and warns (:class:`SizeMismatchWarning`) on clouds of
    very different sizes."""
    src = check_cloud("source", src, min_points)
    tgt = check_cloud("target", tgt, min_points)
    _warn_on_size_mismatch(src, tgt)
    return src, tgt


def sample_and_normalise(src: np.ndarray, tgt: np.ndarray, settings: InferenceSettings) -> Normalised:
    """Stage 1 for one pair of clouds :func:`check_pair` checked: each resampled to ``settings.n_points`` by
    farthest-point sampling, both moved into the unit sphere (:func:`normalise`)."""
    src_idx = farthest_point_sample(src, settings.n_points, seed=settings.seed, pool=settings.fps_pool)
    tgt_idx = farthest_point_sample(tgt, settings.n_points, seed=settings.seed + 1, pool=settings.fps_pool)
    src_n, tgt_n, src_centre, tgt_centre, scale = normalise(src[src_idx], tgt[tgt_idx], settings.centring)
    return Normalised(
        src, tgt, src_idx, tgt_idx, src_n.astype(np.float32), tgt_n.astype(np.float32), src_centre, tgt_centre, scale
    )


def _warn_on_size_mismatch(src: np.ndarray, tgt: np.ndarray) -> None:
    """Warns where the radius of src (N, 3) or tgt (M, 3) is :data:`SIZE_RATIO_WARNING` times the other's."""
    radius = [float(np.linalg.norm(c - c.mean(axis=0), axis=1).max()) for c in (src, tgt)]
    big = int(radius[1] > radius[0])
    ratio = radius[big] / radius[1 - big]
    if ratio >= SIZE_RATIO_WARNING:
        names = ("source", "target")
        warnings.warn(
            f"{names[big]} is {ratio:,.0f} times the size of {names[1 - big]} (radius {radius[big]:.4g} "
            f"against {radius[1 - big]:.4g}): are both in the same units, and free of stray far-off points? "
            "A rigid motion cannot rescale one onto the other",
            SizeMismatchWarning,
            stacklevel=5,
        )
