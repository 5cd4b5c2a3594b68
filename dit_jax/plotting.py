"""Pictures of registrations, drawn with matplotlib off-screen (no display needed).

* :func:`pyplot` -- matplotlib's pyplot on the Agg backend, for every figure the package writes.
* :func:`plot_registration` -- two clouds before and after a registration, seen from two viewpoints, with the
  estimated motion (and its error, where the truth is known) in the title: what ``dit-register --plot``,
  :meth:`dit_jax.registration.Result.plot` and evaluate.py's worst-pair pictures draw.
"""

from __future__ import annotations

import os

import numpy as np

from dit_jax.geometry import rotation_angle_deg

#: Points drawn per cloud at most (a random, seeded subset of larger clouds), so scans draw in a second.
MAX_DRAWN = 4000
#: (elevation, azimuth) of the two views, degrees.
VIEWS = ((25.0, -60.0), (25.0, 60.0))


def pyplot():
    """matplotlib.pyplot on the Agg backend (writes files; needs no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _subset(points: np.ndarray, seed: int) -> np.ndarray:
    if len(points) <= MAX_DRAWN:
        return points
    return points[np.random.default_rng(seed).choice(len(points), MAX_DRAWN, replace=False)]


def describe(rotation: np.ndarray, translation: np.ndarray, *, inlier_ratio: float | None = None,
             fitness: float | None = None, truth: tuple[np.ndarray, np.ndarray] | None = None) -> str:
    """One line: the motion's angle and shift, its evidence and (with ``truth`` = (R, t)) its errors."""
    parts = [f"rotation {rotation_angle_deg(rotation):.2f} deg, translation {np.linalg.norm(translation):.4g}"]
    if inlier_ratio is not None:
        parts.append(f"inlier ratio {inlier_ratio:.2f}")
    if fitness is not None:
        parts.append(f"fitness {fitness:.2f}")
    if truth is not None:
        error = rotation_angle_deg(np.asarray(rotation).T @ np.asarray(truth[0]))
        parts.append(f"error {error:.2f} deg, {np.linalg.norm(np.asarray(translation) - truth[1]):.3g}")
    return "; ".join(parts)


def draw_registration(fig, row: int, rows: int, src: np.ndarray, tgt: np.ndarray, rotation: np.ndarray,
                      translation: np.ndarray, label: str = "estimate") -> None:
    """Fills one row of ``fig`` (of ``rows``) with four 3-D panels: before and after, from each of
    :data:`VIEWS`. src (N, 3), tgt (M, 3); ``tgt ~ src @ rotation.T + translation``."""
    src = _subset(np.asarray(src, np.float64), 0)
    tgt = _subset(np.asarray(tgt, np.float64), 1)
    moved = src @ np.asarray(rotation).T + np.asarray(translation)
    # Percentiles, not extremes: a few stray points of a scan would otherwise shrink the shape to a dot.
    everything = np.concatenate([src, tgt, moved])
    low, high = np.percentile(everything, 1, axis=0), np.percentile(everything, 99, axis=0)
    centre, half = (low + high) / 2, (high - low).max() / 2
    size = max(0.3, 4000.0 / max(len(src), len(tgt)))
    for col, ((elev, azim), (moving, stage)) in enumerate(
            [(v, m) for m in ((src, "before"), (moved, f"after ({label})")) for v in VIEWS]):
        ax = fig.add_subplot(rows, 4, 4 * row + col + 1, projection="3d")
        ax.scatter(*tgt.T, s=size, c="tab:blue", alpha=0.5, label="target", depthshade=False)
        ax.scatter(*moving.T, s=size, c="tab:red" if stage == "before" else "tab:green", label="source",
                   depthshade=False)
        ax.view_init(elev=elev, azim=azim)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
            setter(c - 1.1 * half, c + 1.1 * half)
        ax.set_axis_off()
        ax.set_title(f"{stage}, view {col % 2 + 1}", fontsize=8)
        if col == 0:
            ax.legend(fontsize=7, loc="upper left", markerscale=max(1.0, 6.0 / size))


def plot_registration(path: str | os.PathLike, src: np.ndarray, tgt: np.ndarray, rotation: np.ndarray,
                      translation: np.ndarray, *, title: str | None = None, inlier_ratio: float | None = None,
                      fitness: float | None = None, truth: tuple[np.ndarray, np.ndarray] | None = None,
                      label: str = "estimate") -> str:
    """Writes a PNG of src (N, 3) and tgt (M, 3) before and after ``(rotation, translation)`` to ``path``,
    with :func:`describe` under ``title``; returns the path."""
    plt = pyplot()
    fig = plt.figure(figsize=(13, 3.8))
    draw_registration(fig, 0, 1, src, tgt, rotation, translation, label)
    line = describe(rotation, translation, inlier_ratio=inlier_ratio, fitness=fitness, truth=truth)
    fig.suptitle(f"{title}\n{line}" if title else line, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return os.fspath(path)
