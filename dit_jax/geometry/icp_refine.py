"""DIT's refinement (:func:`refine`): several ICP runs from the estimate it is handed and from searched starts
(offsets of a translation grid, turned copies for clouds at any rotation), descending side by side, the
best trimmed fit kept; never a motion that fits worse than the estimate."""

from __future__ import annotations

import dataclasses

import numpy as np

from dit_jax.geometry import icp, neighbours

#: DIT's refinement (:func:`refine`; ``register(refine="icp")``, evaluate.py's ``DIT+ICP``): the ICP runs it
#: tries from the estimate it is handed, as (method, pairing distances in units of the clouds' radius, trim).
#: No single run suits every pair: point-to-point pairs shared points exactly, point-to-plane slides
#: independently sampled surfaces together, and trimmed runs keep partial views from being pulled by the
#: parts one view lacks. Chosen on validation pairs of training shapes (docs/refinement_check.md).
REFINE_CANDIDATES = (
    ("point_to_point", (0.1, 0.05), None),
    ("point_to_point", (0.1, 0.05, 0.02), None),
    ("point_to_plane", (0.1, 0.05, 0.02), None),
    ("point_to_point", (0.1, 0.05, 0.02), 0.5),
    ("point_to_plane", (0.1, 0.05), 0.5),
)


#: Each stage of a :func:`refine` run stops after this many iterations, or once an update moves no point by
#: more than :data:`REFINE_TOLERANCE` times the stage's pairing distance (:func:`icp`'s ``tolerance``).
REFINE_ITERATIONS = 50


REFINE_TOLERANCE = 1e-7


#: :func:`refine` never takes a run that moves the source points by more than this share of the clouds'
#: radius on average from the estimate it was handed (None: no limit): ICP from a start that far off slides
#: partial views into each other rather than correcting them.
MAX_SHIFT = 0.5


#: :func:`refine` also descends from the estimate moved by the ``starts`` best offsets, by :func:`~dit_jax.geometry.icp.trimmed_fit`
#: at the estimate's rotation, of a grid -span..span in steps of ``step`` (units of the clouds' radius) on
#: each axis: on noisy partial views ICP slides the two along each other and stops 0.2-0.3 off in
#: translation, and no start near the estimate leads back (validation: docs/refinement_check.md).
TRANSLATION_SEARCH = (0.3, 0.1, 3)


#: Source points (a seeded random subset) that score the translation grid of :func:`refine`.
GRID_POINTS = 500


#: :func:`best_start` keeps the first estimate (the unturned start's) unless another fits the clouds better
#: by this factor (its score below this share of the first's): a symmetric shape fits a turned copy of
#: itself nearly as well as the truth, and where the motion is small the unturned start is the right one.
#: Chosen on validation pairs of training shapes, three settings that share no point, turned 0-180 degrees,
#: as the value that keeps the unturned start's accuracy for small turns and gains most beyond
#: (docs/refinement.md, "Clouds at any rotation").
START_MARGIN = 0.7


#: The short ICP of :func:`start_scores`, which ranks the starts: pairing distances in units of the clouds' radius.
START_DISTANCES = (0.1, 0.05)


def start_scores(
    src: np.ndarray,
    tgt: np.ndarray,
    starts: tuple[np.ndarray, np.ndarray],
    *,
    scale: float = 1.0,
    max_points: int = 500,
    seed: int = 0,
) -> np.ndarray:
    """How well each of several estimates of one motion lays src (N, 3) onto tgt (M, 3) after a short
    point-to-point ICP from it (:data:`START_DISTANCES` times ``scale``): (K,) :func:`~dit_jax.geometry.icp.trimmed_fit` scores of
    where the ICP ends, lower is better, for ``starts``: rotations (K, 3, 3) and translations (K, 3).
    ``max_points``: the ICP and the score use a seeded random subset of this many source points."""
    from scipy.spatial import cKDTree

    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    tree = cKDTree(tgt)
    rotations, translations = (np.asarray(a, np.float64) for a in starts)
    scores = []
    for rotation, translation in zip(rotations, translations):
        run = icp.icp(
            src,
            tgt,
            rotation,
            translation,
            distances=tuple(scale * d for d in START_DISTANCES),
            max_points=max_points,
            seed=seed,
            tree=tree,
        )
        scores.append(icp.trimmed_fit(src, tree, run.rotation, run.translation, seed=seed, max_points=max_points))
    return np.asarray(scores)


def best_start(scores: np.ndarray, margin: float = START_MARGIN) -> int:
    """Which estimate to go on from (``register(..., rotation_search=True)``), given their
    :func:`start_scores` (K,), the first the preferred one: the best scoring if its score is below ``margin``
    times the first's, else the first (index 0)."""
    scores = np.asarray(scores, np.float64)
    best = int(np.argmin(scores))
    return best if scores[best] < margin * scores[0] else 0


def mean_shift(
    src: np.ndarray,
    rotation_a: np.ndarray,
    translation_a: np.ndarray,
    rotation_b: np.ndarray,
    translation_b: np.ndarray,
) -> float:
    """How far two motions place the points of src (N, 3) apart, on average (the clouds' units)."""
    return float(np.mean(np.linalg.norm(src @ (rotation_a - rotation_b).T + (translation_a - translation_b), axis=1)))


def _translation_offsets(span: float, step: float) -> np.ndarray:
    """(G, 3) the offsets of a cubic grid, -span..span in steps of ``step`` on each axis, zero excluded."""
    axis = np.arange(-span, span + step / 2, step)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return grid[np.linalg.norm(grid, axis=1) > step / 2]


def refine(
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    scale: float = 1.0,
    seed: int = 0,
    max_shift: float | None = MAX_SHIFT,
    rounds: int = 2,
    max_points: int = 2_000,
    max_target_points: int | None = icp.TARGET_POINTS,
    translation_search: tuple[float, float, int] | None = TRANSLATION_SEARCH,
    workers: int | None = None,
) -> icp.ICPResult:
    """DIT's refinement of a global estimate: the best fit among several ICP runs and the estimate itself.

    Each round runs every :data:`REFINE_CANDIDATES` ICP from the current estimate (distances times
    ``scale``, the clouds' radius) and keeps whichever motion -- one of those runs or the current estimate
    -- has the lowest :func:`~dit_jax.geometry.icp.trimmed_fit`; the next round starts from it. So the estimate comes back
    unchanged (``iterations`` 0) where no run lays the clouds on each other better: an exact start on
    shared points, or a start ICP would only slide along a partial view. Runs that move the source points
    more than ``max_shift`` times ``scale`` on average from the estimate handed in are never taken.

    Then, unless the fit is already exact, the same descent runs again from a few shifted starts: the
    offsets of a translation grid (``translation_search``, see :data:`TRANSLATION_SEARCH`) that fit best at
    the estimate's rotation. The best fit of all is returned, so the result never fits worse than the plain
    descent's.

    Args: src (N, 3), tgt (M, 3), the estimate (3, 3), (3,), as :func:`icp`; ``rounds`` (at least 1) stops
    early once a round keeps its start; ``max_points``: the runs and the fit use a seeded random subset of
    this many source points, which bounds the time on large scans; ``max_target_points``: likewise for the
    target (:data:`~dit_jax.geometry.icp.TARGET_POINTS`; None: the whole target); ``translation_search``: (span, step, starts) in
    units of ``scale``, or None for the plain descent; ``workers``: threads for the nearest-point queries
    (:func:`~dit_jax.geometry.neighbours.nearest_points`; default: the machine's cores; any number gives the same result). The plain and the searched descents run side by side (:func:`~dit_jax.geometry.icp.runs_side_by_side`).
    Returns :class:`~dit_jax.geometry.icp.ICPResult` (fitness and rmse at the finest candidate distance).
    """
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    start = (np.asarray(rotation, np.float64), np.asarray(translation, np.float64))
    if max_target_points:
        tgt = icp.thinned(tgt, max_target_points, seed)
    # The runs and the fit use one seeded subset of the source (icp's and trimmed_fit's own).
    runs_src = icp.subset(src, max_points, seed)
    tree = neighbours.nearest_points(tgt, workers=workers)
    score = lambda r, t: icp.trimmed_fit(runs_src, tree, r, t, seed=seed, max_points=max_points)  # noqa: E731
    starts = [start]
    if translation_search is not None:
        starts += _searched_starts(src, tree, start, scale, seed, translation_search)
    # The searched descents run beside the plain one, though they count only where its fit is not exact.
    normals = neighbours.estimate_normals(tgt, tree=tree)
    descents = _descents(src, runs_src, tgt, tree, normals, score, start, starts, scale, rounds, max_shift)
    (best, best_score, iterations), searched = descents[0], descents[1:]
    # An exact fit (shared points at the true pose) cannot be bettered; the search would only cost time.
    if best_score > (1e-6 * scale) ** 2:
        for run, run_score, run_iterations in searched:  # in the grid's order
            iterations += run_iterations
            shift_ok = max_shift is None or mean_shift(src, run[0], run[1], *start) <= max_shift * scale
            if run[2] and shift_ok and run_score < best_score:
                best, best_score = run, run_score
    finest = scale * min(min(distances) for _, distances, _ in REFINE_CANDIDATES)
    final = icp.icp(src, tgt, best[0], best[1], distances=finest, max_iterations=0, tree=tree)
    return dataclasses.replace(final, iterations=iterations if best[2] else 0)


def _descents(
    src, runs_src, tgt, tree, normals, score, start, starts, scale: float, rounds: int, max_shift: float | None
) -> list[tuple[tuple, float, int]]:
    """:func:`refine`'s descent from each of ``starts`` ((R, t) pairs), all side by side: up to ``rounds``
    rounds in which every :data:`REFINE_CANDIDATES` ICP in turn runs from the best motion so far and is kept
    where ``score`` (lower is better) improves and it moves src no further than ``max_shift`` times ``scale``
    from ``start``; a descent stops after a round that keeps nothing. The runs move ``runs_src``, a subset
    of src. A candidate runs once from any one motion: where it comes to a motion it ran from before (the
    next round, after another candidate improved; two descents at one motion), its run is taken as it was.
    Returns, for each start, the best motion (R, t, the iterations of the run that found it; 0: the start
    itself), its score and the iterations of the runs it ran."""

    def runs_from(candidate, motions):  # each run's R, t, iterations and score (None: it moved too far)
        method, distances, trim = candidate
        run = icp.Run(method, tuple(scale * d for d in distances), trim)
        found = icp.runs_side_by_side(
            runs_src, tgt, tree, normals, [r for r, _ in motions], [t for _, t in motions], run,
            max_iterations=REFINE_ITERATIONS, tolerance=REFINE_TOLERANCE,
        )  # fmt: skip
        for rotation, translation, run_iterations in zip(*found):
            too_far = max_shift is not None and mean_shift(src, rotation, translation, *start) > max_shift * scale
            yield rotation, translation, int(run_iterations), None if too_far else score(rotation, translation)

    best = [(r, t, 0) for r, t in starts]
    best_score = [score(r, t) for r, t in starts]
    iterations = [0] * len(starts)
    ran = {}  # (candidate, the motion's bytes) -> runs_from's record of that run
    going = list(range(len(starts)))
    for _ in range(rounds):
        improved = set()
        for candidate in REFINE_CANDIDATES:
            keys = {k: (candidate, best[k][0].tobytes(), best[k][1].tobytes()) for k in going}
            new = {}  # the motions this candidate has not run from, each with the first descent at it
            for k, key in keys.items():
                if key not in ran:
                    new.setdefault(key, k)
            ran.update(zip(new, runs_from(candidate, [best[k][:2] for k in new.values()])))
            for k in going:
                rotation, translation, run_iterations, run_score = ran[keys[k]]
                iterations[k] += run_iterations if new.get(keys[k]) == k else 0
                if run_score is not None and run_score < best_score[k]:
                    best[k], best_score[k] = (rotation, translation, run_iterations), run_score
                    improved.add(k)
        going = [k for k in going if k in improved]
        if not going:
            break
    return list(zip(best, best_score, iterations))


def _searched_starts(src, tree, start: tuple, scale: float, seed: int, search: tuple) -> list[tuple]:
    """:func:`refine`'s further starts: the estimate ``start`` moved by the ``search``'s best offsets (span,
    step, starts; :data:`TRANSLATION_SEARCH`), in the grid's order."""
    span, step, starts = search
    offsets = scale * _translation_offsets(span, step)
    # The grid is scored at the estimate's rotation, on a few hundred points (it only ranks the offsets).
    grid_scores = icp.trimmed_fit(
        src, tree, start[0], start[1] + offsets, seed=seed, max_points=GRID_POINTS, cap=step * scale
    )
    return [(start[0], start[1] + offsets[k]) for k in np.argsort(grid_scores, kind="stable")[:starts]]
