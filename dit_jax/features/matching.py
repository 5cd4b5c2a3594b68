"""Registration by local features: the pipeline's candidate that needs no start and no training data.

Both clouds are thinned on a voxel grid; each kept point gets a normal, turned to face the cloud's viewpoint
(its origin: a scan's sensor in its own frame, :data:`~dit_jax.features.keypoints.VIEWPOINT`), and FPFH features (Rusu et al., "Fast Point
Feature Histograms (FPFH) for 3D Registration", ICRA 2009) from its neighbours, or another descriptor of
:mod:`dit_jax.features.descriptors`. Each source point is matched to its nearest target point in feature
space, the most distinctive matches kept (:func:`_matches`), and the
compatibility-graph estimator (:mod:`dit_jax.features.compatibility`: second-order spatial compatibility, seeds, a
consistent set and a weighted Procrustes per seed) turns the matches into ranked motions; the one that lays
the most thinned source points on the target wins (:func:`_choose`), and point-to-plane ICP on every point (on
about :data:`~dit_jax.features.keypoints.ICP_POINTS` of larger clouds) refines it. It finds a motion at any turn, so it covers what the network never learned: rooms
turned by anything, LiDAR, scans of any object.

Every length is set in the clouds' own scale, so millimetres and metres give the same motion: the voxel is
:data:`~dit_jax.features.keypoints.VOXEL_SPACINGS` point spacings (:func:`dit_jax.geometry.neighbours.point_spacing`), coarser on very large scans so that
the features see about :data:`~dit_jax.features.keypoints.FEATURE_POINTS` points of each cloud (:func:`~dit_jax.features.keypoints.feature_voxel`); normals come from
neighbours within 2 voxels, features from those within 5, lengths agree within :data:`MATCH_VOXELS` voxels,
a point lies on the target within 1.5, and ICP pairs points within 0.4 voxels.

:func:`register_both_ways` registers the source onto the target and the target onto the source, each from
its own matches. Two directions that land on one motion are the evidence the pipeline's verdict reads
(:class:`FeatureEstimate`), with the estimator's runner-up far from the winner (a rival) and the turned twins
of the result (:func:`~dit_jax.features.twins.twin_fit`).

Nothing is drawn at random: a pair gives the same motion on every run.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import time
from typing import NamedTuple

import numpy as np

from dit_jax.features import compatibility, keypoints, twins
from dit_jax.features.descriptors import _o3d

#: Of the estimator's hypotheses with the most matches, how many are checked against every thinned point; and how
#: far from the winner a rival must lie: turned by more degrees, or moving the matched source points' centre by
#: more voxels. Closer motions are the winner's neighbours; a room's rival is a quarter or half turn, or a
#: slide along a corridor (docs/verdict.md).
FINALISTS = 16


RIVAL_DEGREES = 30.0


RIVAL_VOXELS = 20.0


@dataclasses.dataclass(frozen=True)
class FeatureMatch:
    """A feature-based estimate ``tgt ~ src @ rotation.T + translation``, in the caller's units.

    Attributes:
      rotation: (3, 3) float64; translation: (3,) float64.
      inliers: thinned source points the motion lays within 1.5 voxels of the target (0: no estimate,
        the identity).
      voxel: the voxel the features were computed on, in the caller's units.
    """

    rotation: np.ndarray
    translation: np.ndarray
    inliers: int
    voxel: float


@dataclasses.dataclass(frozen=True)
class FeatureEstimate:
    """:func:`register_both_ways`' result for one pair, in the caller's units: each direction refined by ICP.

    Attributes:
      forward: (R (3, 3), t (3,)), source onto target.
      backward: the inverse of the target registered onto the source, as (R, t) of the source onto the target.
      disagreement: degrees between the two rotations.
      offset: distance between the two translations, in point spacings.
      overlap: (2,) the share of source points each lays within 2 point spacings of the target
        (:func:`dit_jax.geometry.icp.overlap`).
      inliers: (2,) each direction's inliers, as :class:`FeatureMatch` counts them (0: that direction
        found nothing).
      rival: (2,) each direction's rival share (:func:`_choose`): the matches that back another motion and not
        the winner, as a share of the winner's own (inf where that direction found nothing). Near 1, two
        motions explain the matches about as well (a room's walls after a quarter turn); the two directions,
        drawn from the same matches, then tend to agree on one of them.
      twin: (2,) each direction's :func:`~dit_jax.features.twins.twin_fit`: how many points a quarter- or half-turned copy of it lays on
        the target, as a share of its own count (near 1: the two cannot be told apart).
      spacing: the pair's point spacing; voxel: the features' voxel (both in the caller's units).
      seconds: wall time, features to ICP.
      clouds: the two clouds as Open3D holds them, for :meth:`~dit_jax.features.twins.twin_fit`.
    """

    forward: tuple[np.ndarray, np.ndarray]
    backward: tuple[np.ndarray, np.ndarray]
    disagreement: float
    offset: float
    overlap: np.ndarray
    inliers: tuple[int, int]
    rival: tuple[float, float]
    twin: tuple[float, float]
    spacing: float
    voxel: float
    seconds: float
    clouds: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    def twin_fit(self, motion: tuple[np.ndarray, np.ndarray]) -> float:
        """:func:`~dit_jax.features.twins.twin_fit` of ``motion`` (R (3, 3), t (3,)) of the source onto the target, on this pair's
        thinned clouds."""
        if self.clouds is None:
            raise ValueError("this estimate keeps no clouds to compare on")
        return twins.twin_fit(*self.clouds, self.voxel, motion)

    @property
    def kept(self) -> tuple[np.ndarray, np.ndarray]:
        """The direction that lays more of the source onto the target (ties: forward)."""
        return self.backward if self.overlap[1] > self.overlap[0] else self.forward

    @property
    def kept_direction(self) -> str:
        return "backward" if self.overlap[1] > self.overlap[0] else "forward"


#: Matches per direction are capped at the estimator's largest bucket; past it, those whose nearest feature is
#: the most distinctive (:func:`_matches`) are kept. On the shared rooms, the 2,048 most distinctive register
#: as many pairs as the 4,096 closest did, and the estimator's second-order product, cubic in the count, takes
#: a fraction of the time (docs/benchmarks.md).
MAX_MATCHES = compatibility.BUCKETS[-1]


#: Two matches are compatible where their lengths in the two clouds differ by less than this many voxels, and
#: a motion brings a match within this many voxels (twice the 5 cm voxel on 3DMatch's fragments, as SC2-PCR
#: tests lengths there).
MATCH_VOXELS = 2.0


class Nearest(NamedTuple):
    """Each query's two nearest neighbours in a pool: ``index`` (Q,) int64 of the nearest, and the Euclidean
    distances to the ``nearest`` and the ``second`` (Q,) float32."""

    index: np.ndarray
    nearest: np.ndarray
    second: np.ndarray

    @property
    def ratio(self) -> np.ndarray:
        """(Q,) nearest over second-nearest distance (Lowe's ratio): low where the match is distinctive; 1 where
        the two tie (and where both are 0)."""
        return np.where(self.second > 0, self.nearest / np.maximum(self.second, 1e-30), 1.0)


def _two_nearest(queries: np.ndarray, pool: np.ndarray, block: int = 512) -> Nearest:
    """The two nearest rows of ``pool`` (P >= 2, D) for each row of ``queries`` (Q, D), from the squared
    distances in blocks of rows: products on contiguous float32 arrays, in place, each block's reductions along
    its rows (in these few dozen dimensions a k-d tree gains nothing)."""
    queries = np.ascontiguousarray(queries, np.float32)
    pool = np.ascontiguousarray(pool, np.float32)
    pool_squares = np.einsum("pd,pd->p", pool, pool)
    index = np.empty(len(queries), np.int64)
    first, second = np.empty(len(queries), np.float32), np.empty(len(queries), np.float32)
    for start in range(0, len(queries), block):
        rows = slice(start, start + block)
        squares = queries[rows] @ pool.T
        squares *= -2.0
        squares += pool_squares[None, :]  # each row lacks its query's own square, which ranks nothing
        local = np.arange(len(squares))
        index[rows] = np.argmin(squares, axis=1)
        first[rows] = squares[local, index[rows]]
        squares[local, index[rows]] = np.inf
        second[rows] = np.min(squares, axis=1)
    query_squares = np.einsum("qd,qd->q", queries, queries)
    return Nearest(
        index, np.sqrt(np.maximum(first + query_squares, 0.0)), np.sqrt(np.maximum(second + query_squares, 0.0))
    )


def _matches(src: keypoints.Cloud, tgt: keypoints.Cloud) -> tuple[np.ndarray, np.ndarray]:
    """Feature matches of each direction: (K, 2) index pairs (source, target), each thinned source point with
    its nearest target point in feature space, and (K', 2) pairs (target, source) the other way; each capped
    at :data:`MAX_MATCHES`, the most distinctive kept (the lowest :attr:`Nearest.ratio`), in row order.

    No mutual filter: at low overlap it discards most of the right matches, and the compatibility estimator
    needs no help telling them from the wrong ones. The two directions' sets differ, so each is some
    evidence for the other."""
    there, back = _two_nearest(src.features, tgt.features), _two_nearest(tgt.features, src.features)

    def capped(found: Nearest):
        rows = np.sort(np.argsort(found.ratio, kind="stable")[:MAX_MATCHES])
        return np.ascontiguousarray(np.stack([rows, found.index[rows]], axis=1), np.int32)

    return capped(there), capped(back)


def _brought_within(
    rotations: np.ndarray, translations: np.ndarray, src_matched: np.ndarray, tgt_matched: np.ndarray, distance: float
) -> np.ndarray:
    """Which of the K matches each of the (H, 3, 3), (H, 3) motions brings within ``distance``: (H, K) bool."""
    moved = np.einsum("hij,kj->hki", rotations, src_matched) + translations[:, None]
    return np.sum((moved - tgt_matched[None]) ** 2, axis=2) < distance**2


def _estimate(
    src: keypoints.Cloud, tgt: keypoints.Cloud, matches: np.ndarray, voxel: float
) -> tuple[np.ndarray, int, float]:
    """The global motion from (K, 2) feature ``matches`` of the thinned clouds: (4 x 4 motion, inliers, rival
    share). :func:`dit_jax.features.compatibility.estimate_motions` gives one motion per seed, ranked by the matches each brings
    within :data:`MATCH_VOXELS` voxels; :func:`_choose` picks one."""
    if len(matches) < 3:
        return np.eye(4), 0, np.inf
    src_matched = np.asarray(src.thinned.points)[matches[:, 0]]
    tgt_matched = np.asarray(tgt.thinned.points)[matches[:, 1]]
    found = compatibility.estimate_motions(src_matched, tgt_matched, MATCH_VOXELS * voxel)
    if found.matches[0] < 3:
        return np.eye(4), 0, np.inf
    return _choose(src, tgt, src_matched, tgt_matched, found, voxel)


def _choose(
    src: keypoints.Cloud, tgt: keypoints.Cloud, src_matched, tgt_matched, found, voxel: float
) -> tuple[np.ndarray, int, float]:
    """The winner among the hypotheses ``found`` (:class:`dit_jax.features.compatibility.Hypotheses`) of matches
    src_matched <-> tgt_matched (K, 3) each: (4 x 4 motion, inliers, rival share).

    Of the :data:`FINALISTS` with the most matches, the one that lays the most thinned source points within 1.5
    voxels of the thinned target wins; that count is its inliers. Its rival share is the largest number of
    matches one of the hypotheses far from the winner (:data:`RIVAL_DEGREES`, :data:`RIVAL_VOXELS`) brings
    within the distance and the winner does not, divided by the winner's matches: a second explanation of the
    matches that the winner leaves out (a quarter-turned room, a slide along a corridor)."""
    rotations, translations = found.rotation, found.translation
    src_points = np.asarray(src.thinned.points)
    laid_within = 1.5 * voxel
    laid = [
        np.sum(np.isfinite(tgt.tree.query(src_points @ r.T + t, distance_upper_bound=laid_within, workers=-1)[0]))
        for r, t in zip(rotations[:FINALISTS], translations[:FINALISTS])
    ]
    winner = int(np.argmax(laid))  # ties: the motion with more matches
    centre = src_matched.mean(axis=0)
    cosines = (np.einsum("ij,hij->h", rotations[winner], rotations) - 1) / 2
    moved = np.einsum("hij,j->hi", rotations, centre) + translations
    far = (cosines < np.cos(np.radians(RIVAL_DEGREES))) | (
        np.linalg.norm(moved - moved[winner], axis=1) > RIVAL_VOXELS * voxel
    )
    rival = 0.0
    if far.any():
        distance = MATCH_VOXELS * voxel
        within = _brought_within(rotations[far], translations[far], src_matched, tgt_matched, distance)
        winners = _brought_within(rotations[[winner]], translations[[winner]], src_matched, tgt_matched, distance)
        rival = np.max(np.sum(within & ~winners[0], axis=1)) / max(int(found.matches[winner]), 1)
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = rotations[winner], translations[winner]
    return motion, int(laid[winner]), float(rival)


def _icp(src: keypoints.Cloud, tgt: keypoints.Cloud, start: np.ndarray, voxel: float) -> np.ndarray:
    """Point-to-plane ICP over the clouds' ICP points, pairs within 0.4 voxels: the refined 4 x 4 motion."""
    o3d = _o3d()
    reg = o3d.t.pipelines.registration
    found = reg.icp(
        src.icp,
        tgt.icp,
        0.4 * voxel,
        o3d.core.Tensor(np.asarray(start, np.float64)),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(1e-6, 1e-6, 30),  # the legacy API's defaults
    )
    return np.array(found.transformation.numpy(), np.float64)


def _estimate_then_icp(src: keypoints.Cloud, tgt: keypoints.Cloud, matches: np.ndarray, voxel: float):
    """One direction of :func:`register_both_ways`: the global estimate (:func:`_estimate`), then ICP from its
    motion (from the identity where it found none): (4 x 4 motion, inliers, rival share)."""
    motion, inliers, rival = _estimate(src, tgt, matches, voxel)
    return _icp(src, tgt, motion if np.all(np.isfinite(motion)) else np.eye(4), voxel), inliers, rival


def _split(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.array(motion[:3, :3], np.float64), np.array(motion[:3, 3], np.float64)


def match_one_way(
    src: np.ndarray,
    tgt: np.ndarray,
    *,
    spacing: float | None = None,
    seed: int = 0,
    voxel_spacings: float = keypoints.VOXEL_SPACINGS,
    viewpoint: tuple | None = keypoints.VIEWPOINT,
    descriptor: str = keypoints.DESCRIPTOR,
) -> FeatureMatch:
    """Registers src (N, 3) onto tgt (M, 3) by FPFH matches and the compatibility estimator at the voxel of
    :func:`~dit_jax.features.keypoints.feature_voxel`, without ICP.

    Args:
      src, tgt: clouds in any units.
      spacing: their point spacing (default: the larger of the two clouds', :func:`dit_jax.geometry.neighbours.point_spacing`).
      seed: the spacing's subset.
      voxel_spacings: the voxel's point spacings (see :func:`~dit_jax.features.keypoints.feature_voxel`).
      viewpoint: where the normals are turned to face (:data:`~dit_jax.features.keypoints.VIEWPOINT`); None leaves them as estimated.
      descriptor: what the keypoints are matched by (:data:`dit_jax.features.descriptors.DESCRIPTORS`).

    Returns :class:`FeatureMatch`; the identity with ``inliers`` 0 where the estimator finds no motion or a cloud
    occupies fewer than :data:`~dit_jax.features.keypoints.MIN_VOXELS` voxels.
    """
    src, tgt, spacing, voxel, enough = keypoints.prepare(src, tgt, spacing, seed, voxel_spacings)
    if not enough:
        return FeatureMatch(np.eye(3), np.zeros(3), 0, voxel)
    source = keypoints.Cloud(src, voxel, viewpoint=viewpoint, descriptor=descriptor)
    target = keypoints.Cloud(tgt, voxel, viewpoint=viewpoint, descriptor=descriptor)
    motion, inliers, _ = _estimate(source, target, _matches(source, target)[0], voxel)
    if inliers == 0 or not np.all(np.isfinite(motion)):
        return FeatureMatch(np.eye(3), np.zeros(3), 0, voxel)
    return FeatureMatch(*_split(motion), inliers, voxel)


def register_both_ways(
    src: np.ndarray,
    tgt: np.ndarray,
    *,
    seed: int = 0,
    viewpoint: tuple | None = keypoints.VIEWPOINT,
    descriptor: str = keypoints.DESCRIPTOR,
) -> FeatureEstimate | None:
    """Registers src (N, 3) onto tgt (M, 3) and tgt onto src from one set of features, each by the estimator then
    point-to-plane ICP (module docs), at the voxel of :func:`~dit_jax.features.keypoints.feature_voxel` for the clouds' own point spacing
    (the larger of the two, :func:`dit_jax.geometry.neighbours.point_spacing`); ``seed``: the spacing's
    subset. Returns None where a cloud occupies fewer than :data:`~dit_jax.features.keypoints.MIN_VOXELS` voxels (too few features); a
    direction the estimator finds nothing for starts ICP from the identity and counts 0 inliers; ``viewpoint``:
    where the normals face (:data:`~dit_jax.features.keypoints.VIEWPOINT`, None: as estimated); ``descriptor``: what the keypoints are matched
    by (:data:`dit_jax.features.descriptors.DESCRIPTORS`)."""
    started = time.perf_counter()
    src, tgt, spacing, voxel, enough = keypoints.prepare(src, tgt, None, seed, keypoints.VOXEL_SPACINGS)
    if not enough:
        return None
    # Open3D computes each cloud's normals and features on every core already: the clouds are built in turn.
    thin = keypoints.icp_voxel(spacing, max(len(src), len(tgt)))
    source, target = (
        keypoints.Cloud(src, voxel, thin, viewpoint, descriptor),
        keypoints.Cloud(tgt, voxel, thin, viewpoint, descriptor),
    )
    return _both_ways(keypoints.Scan(src, source), keypoints.Scan(tgt, target), spacing, voxel, seed, started)


def register_scans(prepared: keypoints.Scans, source: int, target: int, *, seed: int = 0) -> FeatureEstimate | None:
    """:func:`register_both_ways` of scan ``source`` onto scan ``target`` of ``prepared`` (:func:`~dit_jax.features.keypoints.prepare_scans`),
    from their features as built there; None where either has too few."""
    src, tgt = prepared.scans[source], prepared.scans[target]
    if src is None or tgt is None:
        return None
    return _both_ways(src, tgt, prepared.spacing, prepared.voxel, seed, time.perf_counter())


def _both_ways(
    src: keypoints.Scan, tgt: keypoints.Scan, spacing: float, voxel: float, seed: int, started: float
) -> FeatureEstimate:
    """Both directions of a pair from its scans' features: the estimator then ICP each way, on two threads."""
    from dit_jax.geometry import icp as icp_lib
    from dit_jax.geometry import rigid

    source, target = src.cloud, tgt.cloud
    forward_matches, backward_matches = _matches(source, target)
    # The two directions run on two threads: the estimator's compiled program and ICP release the interpreter.
    with concurrent.futures.ThreadPoolExecutor(2) as threads:
        there = threads.submit(_estimate_then_icp, source, target, forward_matches, voxel)
        back = threads.submit(_estimate_then_icp, target, source, backward_matches, voxel)
        (there, inliers_there, rival_there), (back, inliers_back, rival_back) = there.result(), back.result()
    forward, backward = _split(there), _split(np.linalg.inv(back))
    shares = icp_lib.overlap(src.points, tgt.points, [forward, backward], 2.0 * spacing, seed=seed)
    return FeatureEstimate(
        forward=forward,
        backward=backward,
        disagreement=rigid.rotation_angle_deg(forward[0].T @ backward[0]),
        offset=float(np.linalg.norm(forward[1] - backward[1]) / spacing),
        overlap=shares,
        inliers=(inliers_there, inliers_back),
        rival=(rival_there, rival_back),
        twin=(twins.twin_fit(source, target, voxel, forward), twins.twin_fit(source, target, voxel, backward)),
        spacing=spacing,
        voxel=voxel,
        seconds=time.perf_counter() - started,
        clouds=(source, target),
    )
