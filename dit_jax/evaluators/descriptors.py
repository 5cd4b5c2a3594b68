"""How well a descriptor matches keypoints of real scans with known poses, before any estimator runs.

Two measures, as the descriptor literature reports them on 3DMatch (FCGF's protocol): a pair's inlier ratio,
the share of its nearest-descriptor matches (each source keypoint to its nearest target keypoint in descriptor
space, no mutual filter) that the true motion brings within :data:`INLIER_DISTANCE`; and feature-match recall,
the share of pairs whose inlier ratio passes :data:`FMR_RATIO`. Both are reported on all matches and on the
:data:`dit_jax.features.matching.MAX_MATCHES` most distinctive ones, the set the pipeline's estimator sees.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: A match is right where the true motion brings its source keypoint this close to its target keypoint (metres
#: on 3DMatch); and a pair counts toward feature-match recall where more than this share of its matches are right.
INLIER_DISTANCE = 0.1
FMR_RATIO = 0.05


@dataclasses.dataclass(frozen=True)
class MatchQuality:
    """One pair's nearest-descriptor matches: ``inlier_ratio`` over all source keypoints, ``kept_ratio`` over
    the most distinctive ones the estimator keeps, and ``matches`` (how many source keypoints)."""

    inlier_ratio: float
    kept_ratio: float
    matches: int


def match_quality(
    src_points, src_descriptors, tgt_points, tgt_descriptors, rotation, translation, distance=INLIER_DISTANCE
) -> MatchQuality:
    """The nearest-descriptor matches of src keypoints (N, 3) with descriptors (N, D) onto tgt's (M, 3), (M, D),
    judged by the true motion ``tgt ~ src @ rotation.T + translation`` at ``distance`` (the points' units)."""
    from dit_jax.features import matching

    found = matching._two_nearest(src_descriptors, tgt_descriptors)
    moved = np.asarray(src_points) @ np.asarray(rotation).T + np.asarray(translation)
    right = np.linalg.norm(moved - np.asarray(tgt_points)[found.index], axis=1) < distance
    kept = np.argsort(found.ratio, kind="stable")[: matching.MAX_MATCHES]
    return MatchQuality(float(right.mean()), float(right[kept].mean()), len(right))


def summary(qualities: list[MatchQuality], ratio: float = FMR_RATIO) -> dict:
    """Mean inlier ratios and feature-match recalls of a list of pairs' :class:`MatchQuality`."""
    every = np.array([q.inlier_ratio for q in qualities])
    kept = np.array([q.kept_ratio for q in qualities])
    return {
        "pairs": len(qualities),
        "inlier_ratio": float(every.mean()),
        "fmr": float(np.mean(every > ratio)),
        "kept_inlier_ratio": float(kept.mean()),
        "kept_fmr": float(np.mean(kept > ratio)),
    }
