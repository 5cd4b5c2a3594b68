"""Registering your own point clouds: load a model once, then ``register(src, tgt)`` in the caller's units.

    from dit_jax import registration
    model = registration.load()                      # the shipped weights; or load("runs/x/model"), load("a.pth")
    result = model.register(src_points, tgt_points)  # (N, 3), (M, 3) arrays in any units
    moved = result.apply(src_points)                 # result.matrix is the 4x4 transform

What :meth:`Registrar.register` does to a pair, in order:

1. checks both clouds (finite (N, 3) real coordinates, at least :func:`dit_jax.model.min_points` points, not all
   one point) and raises :class:`InputError` naming the cloud otherwise;
2. resamples each cloud to the model's point count by farthest-point sampling (seeded; clouds above
   ``fps_pool`` points are first thinned to ``fps_pool`` uniformly at random, which keeps the cost linear);
   clouds with fewer points than that are used whole;
3. moves both into the unit sphere with one shared offset (the centroid of the two sampled clouds together,
   as in training; with the default ``centring="auto"`` each cloud's own where the two lie more than
   :data:`FAR_APART` radii apart, and always with ``centring="separate"``) and one shared scale (the largest
   distance of a sampled point from its centre), in float64;
4. runs the jitted :func:`dit_jax.model.register` (one compilation per pair of cloud sizes: with both clouds
   at least the model's point count, every call after the first reuses the same program); with
   ``rotation_search``, on the source turned by each of the 24 rotations of a cube, in one batch, and goes on
   from the estimate that fits best after a short ICP (the unturned one unless another fits clearly better),
   so that clouds at any relative rotation register;
5. maps the transform back: with ``x' = (x - c_x) / s``, ``y' = (y - c_y) / s`` and ``y' = R x' + t'``,
   ``y = R x + s t' + c_y - R c_x``;
6. with ``refine="icp"`` (the default), refines that estimate by ICP on the full clouds (a seeded random
   2,000 of the source's points and up to 50,000 of the target's, :data:`dit_jax.icp.TARGET_POINTS`;
   :func:`dit_jax.icp.refine`: the best trimmed fit among several ICP runs, :data:`dit_jax.icp.REFINE_CANDIDATES`,
   from the estimate and from the best offsets of a translation grid, distances times ``s``, chosen on
   validation pairs), and recomputes the fitness for the refined motion;
7. judges the result (the verdict; ``verdict_rule="agreement"``, the default): the same steps 4-6 register the
   target onto the source (the two directions' refinements run in two threads), and the result is trusted
   where that motion's inverse lies within ``max_disagreement`` degrees of the result's (a threshold per
   refinement, chosen on validation pairs). A right result is the same found from either side; a wrong one
   rarely is. ``verdict_rule="fitness"`` skips the
   second registration and trusts a result where at least ``min_fitness`` of the sampled source points land
   on the target (cheaper; it flags right results on partial views). With ``best_direction`` (ICP and the
   agreement verdict only) the result is whichever of the two refined motions, the forward one or the inverse
   of the target-onto-source one, lays the source onto the target better (:func:`dit_jax.icp.fits_better`);
   the agreement between them, and so the verdict, is the same either way.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import importlib.resources
import os
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax import geometry, icp as icp_lib
from dit_jax import model as model_lib
from dit_jax.configs import DITConfig

#: Where the weights that ship with the package live (see README, "Shipped weights").
SHIPPED_WEIGHTS = "weights/dit-cpu-modelnet40"
#: The verdict's default: a result is trusted when at least this share of the sampled source points lands
#: within ``fitness_radius`` point spacings of the target (a checkpoint may record its own, measured, as
#: ``verdict_min_fitness``; see README, "Is the result right?").
DEFAULT_MIN_FITNESS = 0.5
#: What :meth:`Registrar.register` can do after the network: nothing, or ICP (:mod:`dit_jax.icp`).
REFINEMENTS = ("none", "icp")
#: Where :meth:`Registrar.register` centres the two clouds (step 3 above; :data:`FAR_APART`).
CENTRINGS = ("auto", "shared", "separate")
#: How :meth:`Registrar.register` judges a result (step 7 above).
VERDICTS = ("agreement", "fitness")
#: The agreement verdict's thresholds (degrees between the result and the inverse of the target-onto-source
#: registration) per refinement, where a checkpoint records none (``verdict_max_disagreement``): the first ones
#: ``scripts/choose_inference.py`` chose (2026-11-27, for the third training stage's weights). The shipped
#: checkpoint records its own, 0.5 for both since 2026-12-02 (README, "Is the result right?").
DEFAULT_MAX_DISAGREEMENT = {"none": 3.0, "icp": 6.0}
#: The default of :class:`Registrar`'s ``best_direction``. On validation pairs it raised DIT+ICP's share within
#: 5 degrees on four of ten settings and lowered it on none (docs/BENCHMARKS.md, "DIT+ICP from both
#: directions"); on by default since the sixth training stage's weights, with which every evaluation in docs/
#: was re-measured.
DEFAULT_BEST_DIRECTION = True
#: The turns of the source that ``rotation_search`` starts the network from: the 24 rotations of a cube, the
#: identity first (:func:`dit_jax.geometry.cube_rotations`). Every rotation lies within 62.8 degrees of one, and
#: DIT+ICP handles independently sampled clouds up to about 75 degrees from its start (README "What it reaches").
SEARCH_TURNS = geometry.cube_rotations()


#: ``centring="auto"`` (:class:`Registrar`) centres each cloud on its own centroid where the two sampled clouds'
#: centroids lie more than this many times the larger one's radius apart, else both on their common centroid.
#: Centred together, clouds far apart shrink to two specks in the unit sphere: a dragon pair moved 1000 scan
#: sizes apart came back suspect, a million apart 177 degrees off, where each on its own centroid stays right;
#: up to 30 sizes (60 radii) both work, and a few radii apart the common centroid did a little better with ICP
#: on independently sampled ModelNet40 halves (docs/BENCHMARKS.md, "Clouds far apart"). Training offsets the
#: target by up to 0.87 radii.
FAR_APART = 10.0
#: :meth:`Registrar.register` warns (:class:`SizeMismatchWarning`) where one cloud's radius (the largest
#: distance of one of its points from its centroid) is this many times the other's: two views of one
#: object differ far less, clouds in millimetres and metres 1000 times, and a rigid motion cannot rescale.
SIZE_RATIO_WARNING = 10.0


class InputError(ValueError):
    """A cloud handed to :meth:`Registrar.register` that DIT cannot register; the message names it."""


class SizeMismatchWarning(UserWarning):
    """The two clouds differ in size far more than views of one object do: most likely different units."""


@dataclasses.dataclass(frozen=True)
class Result:
    """A registration, in the caller's units: ``tgt ~ src @ rotation.T + translation``.

    Attributes:
      rotation: (3, 3) float64.
      translation: (3,) float64.
      matrix: (4, 4) float64 homogeneous transform.
      source_indices: (n,) rows of the caller's source cloud the model saw.
      correspondences: (n,) rows of the caller's target cloud matched to them in the last iteration.
      confidence: (n,) the last iteration's Procrustes weight of each such source point, in [0, 1].
      inlier_ratio: share of the sampled source points GMCCE accepted in the last kept iteration.
      fitness: share of the sampled source points the estimate lays within ``fitness_radius`` point spacings
        of the target (see :func:`dit_jax.geometry.fitness`).
      seconds: wall time of the network calls (excluding sampling and a first call's compilation; both
        directions under the agreement verdict; with ``rotation_search``, the starts' short ICPs too).
      refinement: "icp" where ICP refined the network's estimate, else None.
      refine_seconds: wall time of the refinement (0 without one; both directions under the agreement verdict).
      verdict: True ("trusted") where the model's own evidence confirms the result (``agreement <=
        max_disagreement``, or with ``verdict_rule="fitness"``, ``fitness >= min_fitness``), False ("suspect")
        where it does not: trusted results are right (within 5 degrees) about 19 times in 20, but a suspect one
        is not necessarily wrong (on clouds that share no point most suspect DIT+ICP results are right; README,
        "Is the result right?").
      min_fitness: the fitness verdict's threshold.
      agreement: degrees between the rotation and the inverse of the one found registering the target onto
        the source (refined alike); NaN where the fitness verdict did not measure it.
      max_disagreement: the agreement verdict's threshold (degrees).
      verdict_rule: "agreement" or "fitness": which of the two decided ``verdict``.
      direction: "forward" (the source registered onto the target) or "backward" (the inverse of the target
        registered onto the source, kept by ``best_direction`` where it fits better).
      start_turn: with ``rotation_search``, the angle (degrees) of the turn of its source that the kept
        direction's network estimate started from; 0 for the unturned start (and without the search).
      agreement_band: how often results like this one were right, where the checkpoint records it
        (``verdict_agreement_bands``, from the validation pairs its threshold was chosen on): ``(low, high,
        pairs, right)``, the band of agreement (low, high] degrees this result's agreement falls in, how many
        validation results fell in it and how many of those were within 5 degrees of the truth; None where
        the checkpoint records no bands, the verdict measured no agreement, or the band held fewer than
        :data:`MIN_BAND_PAIRS` pairs. A suspect result 0.5-1 degrees from agreeing is far likelier right
        than one 30 degrees from it; this says how much, on the validation data.
    """

    rotation: np.ndarray
    translation: np.ndarray
    matrix: np.ndarray
    source_indices: np.ndarray
    correspondences: np.ndarray
    confidence: np.ndarray
    inlier_ratio: float
    fitness: float
    seconds: float
    verdict: bool = True
    min_fitness: float = DEFAULT_MIN_FITNESS
    refinement: str | None = None
    refine_seconds: float = 0.0
    agreement: float = float("nan")
    max_disagreement: float = float("nan")
    verdict_rule: str = "fitness"
    direction: str = "forward"
    start_turn: float = 0.0
    agreement_band: tuple | None = None

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Moves (N, 3) points by the estimated transform."""
        return np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def to_json(self) -> dict:
        return {"matrix": self.matrix.tolist(), "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist(), "inlier_ratio": self.inlier_ratio,
                "fitness": self.fitness,
                "verdict": "trusted" if self.verdict else "suspect", "verdict_rule": self.verdict_rule,
                "min_fitness": self.min_fitness,
                "agreement_deg": None if np.isnan(self.agreement) else self.agreement,
                "max_disagreement_deg": None if np.isnan(self.max_disagreement) else self.max_disagreement,
                "mean_confidence": float(self.confidence.mean()), "points_used": int(len(self.source_indices)),
                "seconds": self.seconds, "refinement": self.refinement, "refine_seconds": self.refine_seconds,
                "direction": self.direction, "start_turn_deg": self.start_turn,
                "agreement_band": None if self.agreement_band is None else dict(zip(
                    ("low_deg", "high_deg", "validation_pairs", "within_5_deg"), self.agreement_band))}

    def evidence(self) -> str:
        """One line of what the verdict rests on, e.g. for a report or a warning."""
        if self.verdict_rule == "agreement":
            line = (f"registering the target onto the source gives a rotation {self.agreement:.2f} deg from "
                    f"this one's inverse (trusted up to {self.max_disagreement:g} deg)")
            if self.agreement_band is not None:
                low, high, pairs, right = self.agreement_band
                band = f"disagreed by more than {low:g}" if high is None else f"agreed within {low:g}-{high:g}"
                line += (f"; of the {pairs} validation results that {band} deg, "
                         f"{100 * right / pairs:.0f} % were within 5 deg")
            return line
        return (f"{100 * self.fitness:.0f} % of the sampled source points land on the target "
                f"(trusted from {100 * self.min_fitness:.0f} %)")

    def plot(self, path: str | os.PathLike, src, tgt, *, truth: tuple | None = None, title: str | None = None) -> str:
        """Writes a PNG of ``src`` (N, 3) and ``tgt`` (M, 3), the clouds this result registered, before and
        after the motion from two viewpoints, with the motion, inlier ratio and fitness in the title (and the
        error where ``truth`` = (R (3, 3), t (3,)) is given). Returns ``path``."""
        from dit_jax import plotting

        return plotting.plot_registration(path, np.asarray(src), np.asarray(tgt), self.rotation, self.translation,
                                          title=title, inlier_ratio=self.inlier_ratio, fitness=self.fitness,
                                          truth=truth, label="DIT + ICP" if self.refinement else "DIT")


def farthest_point_sample(points: np.ndarray, n: int, *, seed: int = 0, pool: int | None = None) -> np.ndarray:
    """Indices of ``n`` points spread over the cloud by farthest-point sampling.

    Each point taken is the one farthest from all taken before (ties: the lowest index), starting from a
    seeded random point. Runs as one jitted loop (:func:`_farthest_points`): 0.05 s for 1000 of the Stanford
    Dragon's 41,841 points on two CPU cores, against 0.13 s for the float64 NumPy loop it replaced. It works
    in float32: the indices are the float64 loop's but where two candidates tie within float32 rounding
    (25 of the dragon's 30 samplings identical; the other 5 part after 554 to 934 of 1000 points).

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
    padded[:, :len(cloud)] = cloud.T
    chosen = _farthest_points(padded, np.int32(len(cloud)), np.int32(first), n)
    return candidates[np.asarray(chosen, np.int64)]


@functools.partial(jax.jit, static_argnames=("n",))
def _farthest_points(xyz: jax.Array, count: jax.Array, first: jax.Array, n: int) -> jax.Array:
    """Farthest-point sampling of the first ``count`` columns of ``xyz`` (3, P), from column ``first``.

    Coordinates as three rows and the arg-max as a max then a min over indices: XLA's CPU backend vectorises
    both, where a (P, 3) layout and ``jnp.argmax`` (one reduction of value-index pairs) run 6x slower.
    Padding columns start at distance -1 and are never taken. Returns (n,) int32.
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
        raise InputError(f"{name}: {len(array)} points; the model needs at least {min_points}")
    extent = float(np.ptp(array, axis=0).max())
    if extent <= 1e-9 * max(1.0, float(np.abs(array).max())):
        raise InputError(f"{name}: all {len(array)} points are the same point")
    # A line leaves the rotation about itself undetermined, whatever the other cloud. Its spread across the
    # line is zero up to rounding; a millionth of the spread along it is a line in float32, the network's type.
    centred = array - array.mean(axis=0)
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred), 0.0))  # ascending
    if spread[1] <= 1e-6 * spread[2]:
        raise InputError(f"{name}: its {len(array)} points lie on one line, so no rotation about that line "
                         f"can be told from another")
    return array


class Registrar:
    """A model loaded once, registering pairs of clouds of any size, scale and offset.

    Args:
      params, config: the model (see :func:`load` to read them from a checkpoint).
      n_points: points the network sees per cloud (default 1000, the paper's protocol).
      n_iters: registration iterations (default: the config's).
      seed: farthest-point sampling's start (results are deterministic for a given seed).
      fps_pool: clouds above this many points are thinned at random to it before farthest-point sampling.
      centring: "shared" moves both clouds by the centroid of the two together (the clouds keep their offset,
        as in training, where targets sit up to 0.87 radii away); "separate" moves each to its own centroid,
        for clouds that lie far apart in the caller's frame; "auto" (the default): "separate" where the
        sampled clouds' centroids lie more than :data:`FAR_APART` times the larger radius apart, else
        "shared" (every pair measured in docs/ is "shared" either way).
      min_fitness: with ``verdict_rule="fitness"``, a result whose fitness (the share of sampled source points
        it lays onto the target) is below this gets ``verdict=False``.
      refine: the default of :meth:`register`'s ``refine``: "icp" (the default: on every setting and data set
        measured, ModelNet40, the embedded set and real scans, it ends closer to the truth than the network
        alone, for about a second more per pair; docs/eval_*) or "none" (the network alone, fastest).
      precision: the network's matrix products (default: the config's, "highest"; see
        :attr:`dit_jax.configs.DITConfig.precision`).
      verdict_rule: "agreement" (default): also register the target onto the source and trust the result
        where the two agree within ``max_disagreement`` (about twice the time); "fitness": trust it where
        its fitness reaches ``min_fitness`` (one registration).
      max_disagreement: {refine: degrees}, the agreement verdict's thresholds (default
        :data:`DEFAULT_MAX_DISAGREEMENT`; a checkpoint records its own).
      best_direction: with ICP and the agreement verdict, return whichever of the two refined registrations
        (source onto target, or the inverse of target onto source) fits the clouds better; no extra work, the
        verdict already computes both (default :data:`DEFAULT_BEST_DIRECTION`).
      rotation_search: the default of :meth:`register`'s ``rotation_search``: run the network from the 24
        turns of :func:`dit_jax.geometry.cube_rotations` and go on from the one that fits best
        (:func:`dit_jax.icp.best_start`), for clouds at any relative rotation; about 24 times the network's
        time (default False: the network handles rotations up to the training range, README "What it reaches").
      agreement_bands: {refine: [[upper degrees or None, pairs, right], ...]}, how often validation results
        were right band by band of agreement (:func:`dit_jax.evaluation.agreement_bands`; a checkpoint records
        its own), quoted as each result's ``agreement_band``.
    """

    def __init__(self, params, config: DITConfig, *, n_points: int = 1000, n_iters: int | None = None,
                 seed: int = 0, fps_pool: int = 50_000, centring: str = "auto",
                 min_fitness: float = DEFAULT_MIN_FITNESS, refine: str = "icp", precision: str | None = None,
                 verdict_rule: str = "agreement", max_disagreement: dict | None = None,
                 best_direction: bool = DEFAULT_BEST_DIRECTION, rotation_search: bool = False,
                 agreement_bands: dict | None = None):
        _check_refine(refine)
        self.refine = refine
        self.rotation_search = bool(rotation_search)
        if centring not in CENTRINGS:
            raise ValueError(f"centring must be one of {', '.join(map(repr, CENTRINGS))}, got {centring!r}")
        self.centring = centring
        if verdict_rule not in VERDICTS:
            raise ValueError(f"verdict_rule must be one of {', '.join(map(repr, VERDICTS))}, got {verdict_rule!r}")
        self.verdict_rule = verdict_rule
        self.max_disagreement = {**DEFAULT_MAX_DISAGREEMENT, **(max_disagreement or {})}
        self.agreement_bands = dict(agreement_bands or {})
        self.best_direction = bool(best_direction)
        self.config = config if n_iters is None else config.replace(n_iters=n_iters)
        if precision is not None:
            self.config = self.config.replace(precision=precision)
        self.params = jax.tree_util.tree_map(jnp.asarray, params)
        self.n_points = int(n_points)
        self.seed = seed
        self.fps_pool = fps_pool
        self.min_fitness = float(min_fitness)
        if self.n_points < model_lib.min_points(self.config):
            raise ValueError(f"n_points={n_points} is below the model's minimum {model_lib.min_points(self.config)}")

    def register(self, src, tgt, *, refine: str | None = None, rotation_search: bool | None = None) -> Result:
        """Registers ``src`` (N, 3) onto ``tgt`` (M, 3), both in the caller's units; see the module docs.

        ``refine``: "icp" refines the network's estimate by ICP on the full clouds (step 6), "none" does not;
        None: the Registrar's ``refine``. ``rotation_search``: True runs the network from 24 turned starts in
        each direction (step 4, :meth:`_network`), for clouds at any relative rotation; None: the Registrar's."""
        refine = self.refine if refine is None else refine
        search = self.rotation_search if rotation_search is None else bool(rotation_search)
        _check_refine(refine)
        need = model_lib.min_points(self.config)
        src = check_cloud("source", src, need)
        tgt = check_cloud("target", tgt, need)
        src_idx = farthest_point_sample(src, self.n_points, seed=self.seed, pool=self.fps_pool)
        tgt_idx = farthest_point_sample(tgt, self.n_points, seed=self.seed + 1, pool=self.fps_pool)
        src_s, tgt_s = src[src_idx], tgt[tgt_idx]
        src_centre, tgt_centre = src_s.mean(axis=0), tgt_s.mean(axis=0)
        centring = self.centring
        if centring == "auto":
            radius = max(float(np.linalg.norm(c - centre, axis=1).max())
                         for c, centre in ((src_s, src_centre), (tgt_s, tgt_centre)))
            centring = "separate" if np.linalg.norm(src_centre - tgt_centre) > FAR_APART * radius else "shared"
        if centring == "shared":
            src_centre = tgt_centre = np.concatenate([src_s, tgt_s]).mean(axis=0)
        _warn_on_size_mismatch(src, tgt)
        scale = max(float(np.linalg.norm(src_s - src_centre, axis=1).max()),
                    float(np.linalg.norm(tgt_s - tgt_centre, axis=1).max()))
        src_n = ((src_s - src_centre) / scale).astype(np.float32)[None]
        tgt_n = ((tgt_s - tgt_centre) / scale).astype(np.float32)[None]
        started = time.perf_counter()
        rotation, translation, extras, start = self._network(src_n, tgt_n, search)
        both_ways = self.verdict_rule == "agreement"
        if both_ways:
            back_rotation, back_translation, _, back_start = self._network(tgt_n, src_n, search)
        seconds = time.perf_counter() - started
        # Step 5: y = R x + s t' + c_y - R c_x (and the backward motion with the clouds' roles swapped).
        translation = scale * translation + tgt_centre - rotation @ src_centre
        if both_ways:
            back_translation = scale * back_translation + src_centre - back_rotation @ tgt_centre
        fitness = float(extras["fitness"])
        refine_seconds = 0.0
        direction, forward_rotation = "forward", rotation
        if refine == "icp":
            started = time.perf_counter()
            jobs = [(src, tgt, rotation, translation)]
            if both_ways:
                jobs.append((tgt, src, back_rotation, back_translation))
            # The two directions' refinements are independent NumPy and scipy work, which releases the GIL:
            # side by side they take 0.5-0.6 of their serial time on two cores, with identical results.
            with concurrent.futures.ThreadPoolExecutor(len(jobs)) as pool:
                refined, *back = pool.map(lambda job: icp_lib.refine(*job, scale=scale, seed=self.seed), jobs)
            rotation, translation = refined.rotation, refined.translation
            forward_rotation = rotation
            if both_ways:
                (back,) = back
                back_rotation = back.rotation
                inverse = (back.rotation.T, -back.rotation.T @ back.translation)
                if self.best_direction and icp_lib.fits_better(src, tgt, inverse, (rotation, translation)):
                    (rotation, translation), direction, start = inverse, "backward", back_start
            # The fitness, as the model measures it, for the refined motion.
            moved = ((src_s @ rotation.T + translation) - tgt_centre) / scale
            tgt_j = jnp.asarray(tgt_n[0])
            fitness = float(geometry.fitness(jnp.asarray(moved, jnp.float32), tgt_j,
                                             self.config.fitness_radius * geometry.spacing(tgt_j)))
            refine_seconds = time.perf_counter() - started
        max_disagreement = float(self.max_disagreement[refine])
        if both_ways:
            # Between the two directions' motions, whichever of them the result is.
            agreement = geometry.rotation_angle_deg(forward_rotation @ back_rotation)
            verdict = agreement <= max_disagreement
        else:
            agreement, verdict = float("nan"), fitness >= self.min_fitness
        band = _agreement_band(self.agreement_bands.get(refine), agreement)
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = rotation, translation
        return Result(rotation=rotation, translation=translation, matrix=matrix, source_indices=src_idx,
                      correspondences=tgt_idx[np.asarray(extras["correspondences"])],
                      confidence=np.asarray(extras["weights"], np.float64),
                      inlier_ratio=float(extras["inlier_ratio"]), fitness=fitness,
                      seconds=seconds, verdict=bool(verdict), min_fitness=self.min_fitness,
                      refinement=None if refine == "none" else refine, refine_seconds=refine_seconds,
                      agreement=agreement, max_disagreement=max_disagreement, verdict_rule=self.verdict_rule,
                      direction=direction, start_turn=start, agreement_band=band)

    def _network(self, src_n: np.ndarray, tgt_n: np.ndarray, search: bool):
        """The network's estimate for one direction, in the normalised frame: ``(R (3, 3), t (3,), extras of
        the pair, start_turn)``, float64, ``tgt_n ~ src_n @ R.T + t`` for src_n (1, N, 3), tgt_n (1, M, 3).

        With ``search``, the source is turned about its centroid c by each of :data:`SEARCH_TURNS` (Q) and the
        24 pairs go through the network in one batch; each estimate (R', t') of a turned source is one of the
        source itself, ``R = R' Q``, ``t = t' + R' c - R c``, and :func:`dit_jax.icp.best_start` picks the one
        to go on from (the unturned one unless another fits clearly better). ``start_turn``: the angle in
        degrees of the turn it started from (0: unturned)."""
        if not search:
            rotation, translation, extras = jax.device_get(model_lib.register(self.params, src_n, tgt_n, self.config))
            return (np.asarray(rotation[0], np.float64), np.asarray(translation[0], np.float64),
                    {k: v[0] for k, v in extras.items()}, 0.0)
        points = np.asarray(src_n[0], np.float64)
        centre = points.mean(axis=0)
        turned = (points - centre) @ SEARCH_TURNS.transpose(0, 2, 1) + centre
        targets = np.repeat(tgt_n, len(SEARCH_TURNS), axis=0)
        found, shifts, extras = jax.device_get(
            model_lib.register(self.params, turned.astype(np.float32), targets, self.config))
        found = np.asarray(found, np.float64)
        rotations = found @ SEARCH_TURNS
        translations = np.asarray(shifts, np.float64) + found @ centre - rotations @ centre
        k = icp_lib.best_start(icp_lib.start_scores(points, tgt_n[0], rotations, translations, seed=self.seed))
        return (rotations[k], translations[k], {name: v[k] for name, v in extras.items()},
                round(geometry.rotation_angle_deg(SEARCH_TURNS[k]), 6))  # 0, 90, 120 or 180


def _warn_on_size_mismatch(src: np.ndarray, tgt: np.ndarray) -> None:
    """Warns where the radius of src (N, 3) or tgt (M, 3) is :data:`SIZE_RATIO_WARNING` times the other's."""
    radius = [float(np.linalg.norm(c - c.mean(axis=0), axis=1).max()) for c in (src, tgt)]
    big = int(radius[1] > radius[0])
    ratio = radius[big] / radius[1 - big]
    if ratio >= SIZE_RATIO_WARNING:
        names = ("source", "target")
        warnings.warn(f"{names[big]} is {ratio:,.0f} times the size of {names[1 - big]} (radius {radius[big]:.4g} "
                      f"against {radius[1 - big]:.4g}): are both in the same units, and free of stray far-off points? "
                      "A rigid motion cannot rescale one onto the other", SizeMismatchWarning, stacklevel=3)


def _check_refine(refine) -> None:
    if refine not in REFINEMENTS:
        raise ValueError(f"refine must be one of {', '.join(map(repr, REFINEMENTS))}, got {refine!r}")


def shipped_weights() -> str:
    """Path of the weights that ship with the package (a checkpoint directory)."""
    return os.fspath(importlib.resources.files("dit_jax") / SHIPPED_WEIGHTS)


#: :attr:`Result.agreement_band` is quoted only from a band of at least this many validation results.
MIN_BAND_PAIRS = 10


def _agreement_band(bands: list | None, agreement: float) -> tuple | None:
    """The (low, high, pairs, right) of ``bands`` ([[upper or None, pairs, right], ...], increasing) that
    ``agreement`` (degrees) falls in; None without bands or agreement, or for a band of too few pairs."""
    if not bands or not np.isfinite(agreement):
        return None
    low = 0.0
    for high, pairs, right in bands:
        if high is None or agreement <= high:
            return (low, high, int(pairs), int(right)) if pairs >= MIN_BAND_PAIRS else None
        low = high
    return None


def load(checkpoint: str | os.PathLike | None = None, **kwargs) -> Registrar:
    """A :class:`Registrar` from an orbax checkpoint directory, the authors' ``.pth`` weights, or (None) the
    shipped weights. ``kwargs`` go to :class:`Registrar`; ``n_points`` defaults to what the checkpoint
    records for inference, else 1000."""
    from dit_jax import checkpoint as ckpt_lib  # orbax is slow to import; only loading needs it
    from dit_jax import convert

    path = os.fspath(checkpoint) if checkpoint is not None else shipped_weights()
    if checkpoint is None and not os.path.isdir(path):
        raise ckpt_lib.CheckpointError(f"no checkpoint given and the shipped weights are missing ({path})")
    if os.path.isfile(path) and path.endswith((".pth", ".pt", ".t7")):
        state_dict = convert.load_pth(path)
        config = convert.infer_config(state_dict)
        params, extra = convert.from_torch_state_dict(state_dict, config), {}
    else:
        params, config = ckpt_lib.restore(path)
        extra = ckpt_lib.read_extra(path)
    kwargs.setdefault("n_points", extra.get("inference_points") or 1000)
    kwargs.setdefault("min_fitness", extra.get("verdict_min_fitness", DEFAULT_MIN_FITNESS))
    kwargs.setdefault("max_disagreement", extra.get("verdict_max_disagreement"))
    kwargs.setdefault("agreement_bands", extra.get("verdict_agreement_bands"))
    return Registrar(params, config, **kwargs)
