"""How a pair's clouds see their shape: scan-like views (what a range scanner at a viewpoint sees, hidden
points removed) and the samplers that thin a cloud to a size (uniform, a density gradient, farthest points)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

#: Scan-like views: the camera's distance from the shape's centre (radii), Katz's gamma, the largest angle
#: between the two viewpoints (degrees) and the share of the shape's points each view keeps.
SCAN_DISTANCE = 2.0


SCAN_GAMMA = 2.0


SCAN_MAX_VIEW_ANGLE = 60.0


def visible_points(points: np.ndarray, camera: np.ndarray, gamma: float = SCAN_GAMMA) -> np.ndarray:
    """Which of ``points`` (N, 3) a camera at ``camera`` (3,) sees: hidden-point removal (Katz, Tal and Basri,
    "Direct visibility of point sets", 2007). Points are flipped about a sphere around the camera of radius
    ``10 ** gamma`` times the farthest point's distance; those on the convex hull of the flipped points and the
    camera are visible. Larger ``gamma`` sees more. Returns (N,) bool."""
    from scipy.spatial import ConvexHull

    rel = np.asarray(points, np.float64) - camera
    norm = np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-12)
    radius = norm.max() * 10.0**gamma
    flipped = rel + 2.0 * (radius - norm) * rel / norm
    hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))
    seen = np.zeros(len(rel), bool)
    seen[hull.vertices[hull.vertices < len(rel)]] = True
    return seen


def scan_views(shape: np.ndarray, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Indices (k,) of the source's and the target's points of one shape (P, 3): two scan-like views."""
    direction = unit_vectors(rng, 1)[0]
    axis = rng.normal(size=3)
    axis -= (axis @ direction) * direction
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0.0, SCAN_MAX_VIEW_ANGLE))
    # Rodrigues: the target's viewing direction, ``angle`` away from the source's.
    other = direction * np.cos(angle) + np.cross(axis, direction) * np.sin(angle)
    centre = shape.mean(axis=0)
    cameras = centre + SCAN_DISTANCE * direction, centre + SCAN_DISTANCE * other
    seen = [visible_points(shape, camera) for camera in cameras]
    # A point both views see goes to one of them at random, so the clouds share no point.
    coin = rng.random(len(shape)) < 0.5
    owner = np.full(len(shape), -1)
    owner[seen[0] & (~seen[1] | coin)] = 0
    owner[seen[1] & (~seen[0] | ~coin)] = 1
    out = []
    for view in (0, 1):
        own = np.flatnonzero(owner == view)
        if len(own) >= k:
            out.append(rng.choice(own, k, replace=False))
            continue
        # Too few at this density: fill up with the unowned (hidden) points nearest this view's camera.
        spare = np.flatnonzero(owner == -1)
        fill = spare[np.argsort(np.linalg.norm(shape[spare] - cameras[view], axis=1))[: k - len(own)]]
        owner[fill] = view
        out.append(np.concatenate([own, fill]))
    # Both views seeing most of a sparse shape leaves few hidden points to fill with: a view still short
    # takes the points neither cloud holds (the other view's unchosen ones) nearest its camera. Shapes have at
    # least 2k points, so there are always enough; nothing here draws from ``rng``, so every pair that was
    # whole before stays as it was.
    for view in (0, 1):
        short = k - len(out[view])
        if short > 0:
            free = np.setdiff1d(np.arange(len(shape)), np.concatenate(out))
            nearest = free[np.argsort(np.linalg.norm(shape[free] - cameras[view], axis=1))[:short]]
            out[view] = np.concatenate([out[view], nearest])
    return out[0], out[1]


def unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) directions drawn uniformly on the sphere from ``rng``."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


#: The ways :func:`thin` can pick the points a cloud keeps: at random (``uniform``); at random with a density
#: that grows along a random direction, 4-40 times higher at one end of the cloud than at the other
#: (``density``); or spread evenly by farthest-point sampling, as a Poisson-disk sample is (``farthest``).
SAMPLERS = ("uniform", "density", "farthest")


def sample_points(points: np.ndarray, keep: int, rng: np.random.Generator, sampler: str = "uniform") -> np.ndarray:
    """Sorted indices (keep,) of the points of ``points`` (N, 3) that ``sampler`` (one of :data:`SAMPLERS`)
    keeps, drawn from ``rng``."""
    n = len(points)
    if sampler == "uniform":
        return np.sort(rng.choice(n, keep, replace=False))
    if sampler == "density":
        along = np.asarray(points, np.float64) @ unit_vectors(rng, 1)[0]
        along = (along - along.min()) / max(float(np.ptp(along)), 1e-12)
        weights = np.exp(rng.uniform(np.log(4.0), np.log(40.0)) * along)
        return np.sort(rng.choice(n, keep, replace=False, p=weights / weights.sum()))
    if sampler == "farthest":
        points = np.asarray(points, np.float64)
        taken = np.empty(keep, np.int64)
        taken[0] = rng.integers(n)
        gap = np.sum((points - points[taken[0]]) ** 2, axis=1)
        for i in range(1, keep):
            taken[i] = int(np.argmax(gap))
            gap = np.minimum(gap, np.sum((points - points[taken[i]]) ** 2, axis=1))
        return np.sort(taken)
    raise ValueError(f"unknown sampler {sampler!r}; choose one of {', '.join(SAMPLERS)}")


def thin(pairs: Mapping[str, np.ndarray], keep: int, rngs, sampling: str = "uniform") -> dict[str, np.ndarray]:
    """Pairs (a stacked batch, as :meth:`PairDataset.batch` gives) whose clouds keep ``keep`` points each,
    drawn from ``rngs`` (one generator per pair); ``correspondence`` follows the kept points (-1 where a
    source point's counterpart was dropped). ``sampling``: "uniform" (points at random) or "varied" (each
    cloud by one of :data:`SAMPLERS`, drawn at random: the source and the target may differ). Clouds already
    that size are kept as they are."""
    src, tgt = pairs["src"], pairs["tgt"]
    if src.shape[1] < keep or tgt.shape[1] < keep:
        raise ValueError(f"cannot thin clouds of {src.shape[1]} and {tgt.shape[1]} points to {keep}")
    if src.shape[1] == tgt.shape[1] == keep:
        return dict(pairs)
    b = src.shape[0]

    def rows(clouds):
        if sampling == "uniform":
            return np.stack([sample_points(c, keep, rng) for c, rng in zip(clouds, rngs)])
        return np.stack(
            [sample_points(c, keep, rng, SAMPLERS[rng.integers(len(SAMPLERS))]) for c, rng in zip(clouds, rngs)]
        )

    src_rows, tgt_rows = rows(src), rows(tgt)
    # where[i, j]: the new row of the target's old row j (-1: dropped)
    where = np.full((b, tgt.shape[1] + 1), -1, np.int64)
    np.put_along_axis(where, tgt_rows, np.broadcast_to(np.arange(keep), (b, keep)), axis=1)
    old = np.take_along_axis(pairs["correspondence"], src_rows, axis=1)
    return dict(
        pairs,
        src=np.take_along_axis(src, src_rows[..., None], axis=1),
        tgt=np.take_along_axis(tgt, tgt_rows[..., None], axis=1),
        correspondence=np.take_along_axis(where, np.where(old >= 0, old, tgt.shape[1]), axis=1).astype(
            pairs["correspondence"].dtype
        ),
    )
