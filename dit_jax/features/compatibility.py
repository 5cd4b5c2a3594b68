"""A global motion from putative matches by second-order spatial compatibility, as pure jitted functions.

Given K matches ``src[k] <-> tgt[k]`` (most of them wrong, as nearest-feature matches between room scans are),
a rigid motion keeps every distance: two right matches ``i, j`` satisfy ``|x_i - x_j| = |y_i - y_j|`` up to the
noise. The estimator reads the whole K x K table of that test at once, which is dense linear algebra:

1. **First-order compatibility** :func:`compatibility`: ``C_ij = 1`` where the two lengths differ by less
   than ``distance`` (and i != j).
2. **Second-order compatibility** (Chen et al., "SC2-PCR", CVPR 2022): ``S_ij = C_ij * (C @ C)_ij``, the number of
   matches compatible with both i and j. Right matches share many such witnesses; a wrong match that happens
   to fit one right one rarely shares them.
3. **Seeds** :func:`seeds`: each match's spectral confidence (the leading eigenvector of S, by power
   iteration); a match is a seed where no match within ``distance`` of it in the source has a higher one
   (non-maximum suppression), the most confident ``n_seeds`` of them.
4. **Hypotheses** :func:`hypotheses`: for each seed, the ``set_size`` matches most compatible with it (its row
   of S); their own second-order table's leading eigenvector weighs them (local spectral matching) in a
   weighted Procrustes; each motion is then re-fitted twice on every match it brings within ``distance``,
   weighted by how close (a truncated quadratic), which is `vmap` over seeds.
5. Each hypothesis counts the matches it brings within ``distance`` (:func:`score`). The caller ranks them on
   the dense clouds (:mod:`dit_jax.features.matching`), and the runner-up far from the winner is the evidence of
   an ambiguity (a quarter-turned room, a slide along a corridor).

Shapes are fixed by padding the matches to a bucket of :data:`BUCKETS` (``valid`` marks the real ones), so a
handful of compiled programs serve every pair. Everything runs in float32; lengths are in the caller's units.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.geometry import rigid

#: The padded match counts: a pair's matches go into the smallest bucket that holds them (more are cut to the
#: largest by the caller), so at most this many programs are compiled per option set.
BUCKETS = (512, 1024, 2048)
#: Seeds per pair, and matches in each seed's consistent set.
N_SEEDS, SET_SIZE = 100, 40
#: Power-iteration steps for the leading eigenvectors (they converge in a few on such positive matrices).
POWER_STEPS = 15
#: Re-fits of each hypothesis on the matches it brings within the distance.
REFITS = 2


@dataclasses.dataclass(frozen=True)
class Hypotheses:
    """Candidate motions ``tgt ~ src @ rotation.T + translation`` for one set of matches, in numpy.

    Attributes:
      rotation: (H, 3, 3); translation: (H, 3).
      matches: (H,) matches each brings within the distance, best first.
    """

    rotation: np.ndarray
    translation: np.ndarray
    matches: np.ndarray


def bucket(count: int) -> int:
    """The padded size for ``count`` matches: the smallest of :data:`BUCKETS` that holds them, else the largest."""
    for size in BUCKETS:
        if count <= size:
            return size
    return BUCKETS[-1]


def _pairwise_lengths(points: jax.Array) -> jax.Array:
    """(K, K) Euclidean distances between the rows of points (K, 3), centred first.

    From the Gram matrix (one product, where differences would make a (K, K, 3) array): in float32 the squared
    lengths lose about 1e-7 of the cloud's squared radius, far below any match distance worth testing."""
    points = points - jnp.mean(points, axis=0)
    squared = jnp.sum(points * points, axis=1)
    gram = jnp.matmul(points, points.T, precision=jax.lax.Precision.HIGHEST)
    return jnp.sqrt(jnp.maximum(squared[:, None] + squared[None, :] - 2.0 * gram, 0.0))


def compatibility(src: jax.Array, tgt: jax.Array, valid: jax.Array, distance: jax.Array) -> jax.Array:
    """First-order compatibility of K matches src (K, 3) <-> tgt (K, 3): (K, K) float32, 1 where both are
    ``valid`` (K,), distinct, and their lengths in the two clouds differ by less than ``distance``."""
    consistent = jnp.abs(_pairwise_lengths(src) - _pairwise_lengths(tgt)) < distance
    both = valid[:, None] & valid[None, :] & ~jnp.eye(len(src), dtype=bool)
    return (consistent & both).astype(jnp.float32)


def second_order(first: jax.Array) -> jax.Array:
    """``S = C * (C @ C)`` for a (K, K) 0/1 table C: for each compatible pair, how many matches are compatible
    with both, as float32.

    The product is taken on 8-bit integers with 32-bit sums: exact, and on the CPU four to six times faster
    than a float32 product of the same table (docs/benchmarks.md)."""
    ones = first.astype(jnp.int8)
    common = jnp.matmul(ones, ones, preferred_element_type=jnp.int32)
    return first * common.astype(jnp.float32)


def leading_vector(matrix: jax.Array, steps: int = POWER_STEPS) -> jax.Array:
    """The leading eigenvector of a non-negative symmetric (..., K, K) matrix by power iteration from the all-ones
    vector: (..., K), unit length, non-negative; zero where the matrix is zero."""
    vector = jnp.ones(matrix.shape[:-1], matrix.dtype)

    def step(v, _):
        v = jnp.einsum("...ij,...j->...i", matrix, v, precision=jax.lax.Precision.HIGHEST)
        return v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), 1e-20), None

    return jax.lax.scan(step, vector, None, length=steps)[0]


def seeds(src: jax.Array, confidence: jax.Array, valid: jax.Array, distance: jax.Array, n_seeds: int) -> jax.Array:
    """The ``n_seeds`` most confident matches that no valid match within ``distance`` of them in the source
    outranks (ties to the lower index): (n_seeds,) int32 indices (src (K, 3), confidence and valid (K,))."""
    score = jnp.where(valid, confidence, -1.0)
    near = _pairwise_lengths(src) < distance
    order = jnp.arange(len(score))
    beaten = near & (
        (score[None, :] > score[:, None]) | ((score[None, :] == score[:, None]) & (order[None] < order[:, None]))
    )
    peak = valid & ~jnp.any(beaten, axis=1)
    return jax.lax.top_k(jnp.where(peak, score, -2.0), n_seeds)[1]


def _residuals(src: jax.Array, tgt: jax.Array, rotation: jax.Array, translation: jax.Array) -> jax.Array:
    """|R src_k + t - tgt_k| for every match: (K,)."""
    moved = jnp.einsum("ij,kj->ki", rotation, src, precision=jax.lax.Precision.HIGHEST) + translation
    return jnp.linalg.norm(moved - tgt, axis=-1)


def _refit(src, tgt, valid, distance, rotation, translation):
    """One re-fit: weighted Procrustes on the valid matches the motion brings within ``distance``, each weighted
    by ``1 - (r / distance)^2``; the motion as it was where fewer than three are that close."""
    gap = _residuals(src, tgt, rotation, translation)
    weight = jnp.where(valid & (gap < distance), 1.0 - (gap / distance) ** 2, 0.0)
    new_rotation, new_translation = rigid.weighted_procrustes(src, tgt, weight)
    enough = jnp.sum(weight > 0) >= 3
    return jnp.where(enough, new_rotation, rotation), jnp.where(enough, new_translation, translation)


def hypotheses(src, tgt, valid, distance, second, seed_rows, set_size: int = SET_SIZE):
    """One motion per seed (module docs, step 4): rotations (S, 3, 3), translations (S, 3).

    src, tgt (K, 3); valid (K,); second: the (K, K) second-order table; seed_rows: (S,) seed indices."""

    def one(seed):
        strength = second[seed].at[seed].set(jnp.inf)  # the seed first, then its most compatible matches
        members = jax.lax.top_k(jnp.where(valid, strength, -1.0), set_size)[1]
        inside = valid[members] & (strength[members] > 0)
        local = second_order(compatibility(src[members], tgt[members], inside, distance))
        weight = leading_vector(local) * inside
        weight = jnp.where(jnp.sum(weight) > 0, weight, inside.astype(weight.dtype))
        rotation, translation = rigid.weighted_procrustes(src[members], tgt[members], weight)
        for _ in range(REFITS):
            rotation, translation = _refit(src, tgt, valid, distance, rotation, translation)
        return rotation, translation

    return jax.vmap(one)(seed_rows)


def score(src, tgt, valid, distance, rotations, translations) -> jax.Array:
    """How many valid matches each of the (H, 3, 3), (H, 3) motions brings within ``distance``: (H,) int32."""
    gaps = jax.vmap(lambda r, t: _residuals(src, tgt, r, t))(rotations, translations)
    return jnp.sum((gaps < distance) & valid[None], axis=1).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("n_seeds", "set_size"))
def estimate(src, tgt, valid, distance, n_seeds: int = N_SEEDS, set_size: int = SET_SIZE):
    """Steps 1-5 of the module docs on padded matches src, tgt (K, 3) float32 with valid (K,) bool, lengths
    within ``distance`` (a scalar): (rotations (S, 3, 3), translations (S, 3), matches (S,)) for S = n_seeds."""
    first = compatibility(src, tgt, valid, distance)
    second = second_order(first)
    confidence = leading_vector(second)
    rows = seeds(src, confidence, valid, distance, n_seeds)
    rotations, translations = hypotheses(src, tgt, valid, distance, second, rows, set_size)
    return rotations, translations, score(src, tgt, valid, distance, rotations, translations)


def estimate_motions(src: np.ndarray, tgt: np.ndarray, distance: float) -> Hypotheses:
    """The estimator on K matches src (K, 3) <-> tgt (K, 3) in any units (at most ``BUCKETS[-1]``; the caller
    chooses which to keep), lengths compared within ``distance``: every seed's motion, best first.

    The clouds are centred on the source matches' mean before the float32 work, so that coordinates far from
    the origin lose no precision; the motions are returned in the caller's frame, in float64."""
    src, tgt = np.asarray(src, np.float64), np.asarray(tgt, np.float64)
    count = len(src)
    if count > BUCKETS[-1]:
        raise ValueError(f"{count} matches: at most {BUCKETS[-1]} (keep the best)")
    if count < 3:
        return Hypotheses(np.eye(3)[None], np.zeros((1, 3)), np.zeros(1, np.int64))
    size = bucket(count)
    src_centre, tgt_centre = src.mean(axis=0), tgt.mean(axis=0)
    padded_src = np.zeros((size, 3), np.float32)
    padded_tgt = np.zeros((size, 3), np.float32)
    padded_src[:count], padded_tgt[:count] = src - src_centre, tgt - tgt_centre
    valid = np.arange(size) < count
    rotations, translations, counts = jax.device_get(
        estimate(padded_src, padded_tgt, valid, np.float32(distance), n_seeds=min(N_SEEDS, size))
    )
    rotations = np.asarray(rotations, np.float64)
    # x' = x - c_s, y' = y - c_t, y' = R x' + t'  =>  y = R x + t' + c_t - R c_s
    translations = np.asarray(translations, np.float64) + tgt_centre - rotations @ src_centre
    order = np.argsort(-np.asarray(counts), kind="stable")
    return Hypotheses(rotations[order], translations[order], np.asarray(counts, np.int64)[order])
