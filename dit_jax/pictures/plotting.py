"""Pictures of registrations, drawn with matplotlib off-screen (no display needed).

* :func:`pyplot` -- matplotlib's pyplot on the Agg backend, for every figure the package writes.
* :func:`plot_registration` -- two clouds before and after a registration, seen from two viewpoints, with the
  estimated motion (and its error, where the truth is known) in the title: what ``dit-register --plot``,
  :meth:`dit_jax.pipeline.result.Result.plot` and evaluate.py's worst-pair pictures draw.
* :func:`plot_series` -- a series of scans in one frame, each in its own colour, from two sides, beside
  each link's verdict: what ``dit-register-series --plot`` and :meth:`dit_jax.scenes.series.SeriesResult.plot` draw.
"""

from __future__ import annotations

import os

import numpy as np

from dit_jax.geometry.rigid import rotation_angle_deg

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


def describe(
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    inlier_ratio: float | None = None,
    fitness: float | None = None,
    truth: tuple[np.ndarray, np.ndarray] | None = None,
) -> str:
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


def draw_registration(
    fig,
    row: int,
    rows: int,
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    label: str = "estimate",
) -> None:
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
        [(v, m) for m in ((src, "before"), (moved, f"after ({label})")) for v in VIEWS]
    ):
        ax = fig.add_subplot(rows, 4, 4 * row + col + 1, projection="3d")
        ax.scatter(*tgt.T, s=size, c="tab:blue", alpha=0.5, label="target", depthshade=False)
        ax.scatter(
            *moving.T, s=size, c="tab:red" if stage == "before" else "tab:green", label="source", depthshade=False
        )
        ax.view_init(elev=elev, azim=azim)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
            setter(c - 1.1 * half, c + 1.1 * half)
        ax.set_axis_off()
        ax.set_title(f"{stage}, view {col % 2 + 1}", fontsize=8)
        if col == 0:
            ax.legend(fontsize=7, loc="upper left", markerscale=max(1.0, 6.0 / size))


def plot_registration(
    path: str | os.PathLike,
    src: np.ndarray,
    tgt: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    title: str | None = None,
    inlier_ratio: float | None = None,
    fitness: float | None = None,
    truth: tuple[np.ndarray, np.ndarray] | None = None,
    label: str = "estimate",
) -> str:
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


def plot_series(
    path: str | os.PathLike,
    clouds: list[np.ndarray],
    *,
    names: list[str] | None = None,
    links: list[tuple[str, float, float, bool]] | None = None,
    title: str | None = None,
) -> str:
    """Writes a PNG of scans already in one frame, each (N_k, 3) in its own colour, seen along the merged
    cloud's thinnest and middle principal axes (whatever axis is up), and a bar per
    link: ``links`` = (label, agreement in degrees, threshold, trusted), green where trusted, red where
    not trusted, the threshold dashed. Returns the path."""
    plt = pyplot()
    names = names or [f"scan {k}" for k in range(len(clouds))]  # legend entries
    per_scan = max(300, 3 * MAX_DRAWN // max(1, len(clouds)))
    drawn = [
        np.asarray(c, np.float64)[np.random.default_rng(k).choice(len(c), min(len(c), per_scan), replace=False)]
        for k, c in enumerate(clouds)
    ]
    everything = np.concatenate(drawn)
    centre = np.median(everything, axis=0)
    _, _, axes = np.linalg.svd(everything - centre, full_matrices=False)  # rows: most to least spread
    colours = plt.get_cmap("tab20" if len(clouds) > 10 else "tab10")
    panels = 3 if links else 2
    fig, ax_row = plt.subplots(1, panels, figsize=(5.2 * panels, 5.0))
    views = ((0, 1, "seen along its thinnest axis"), (0, 2, "along its middle axis"))
    for ax, (across, up, label) in zip(ax_row, views):
        for k, points in enumerate(drawn):
            flat = (points - centre) @ axes[[across, up]].T
            ax.scatter(*flat.T, s=0.6, color=colours(k % colours.N), label=names[k], rasterized=True)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"all scans in the first one's frame, {label}", fontsize=8)
    if links:
        ax = ax_row[2]
        labels, agreements, thresholds, trusted = zip(*links)
        ax.bar(range(len(links)), agreements, color=["tab:green" if t else "tab:red" for t in trusted])
        for k, threshold in enumerate(thresholds):
            ax.plot([k - 0.4, k + 0.4], [threshold, threshold], "k--", lw=1)
        ax.set_xticks(range(len(links)), labels, rotation=90 if len(links) > 8 else 0, fontsize=7)
        ax.set_ylabel("agreement of the two directions (deg)", fontsize=8)
        ax.set_title("links: green trusted, red not trusted; dashed: threshold", fontsize=8)
    if len(clouds) <= 20:
        handles, labels = ax_row[0].get_legend_handles_labels()
        fig.legend(
            handles, labels, loc="lower center", ncol=min(5, len(clouds)), fontsize=7, markerscale=8, frameon=False
        )
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.04 * (1 + min(20, len(clouds)) // 5), 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return os.fspath(path)
