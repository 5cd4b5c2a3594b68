"""Views a user can turn: one self-contained HTML page (plotly, its script inside) of clouds in one frame.

:meth:`dit_jax.scenes.scene.Scene.plot` draws a scene's placed scans, each in its own colour, and its edges;
:meth:`dit_jax.pipeline.result.Result.plot` draws a registered pair where the file name ends in ``.html``. The page
opens in any browser, offline: drag to turn, scroll to zoom, click a legend entry to hide a cloud.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

#: A page holds at most this many points in all, each cloud thinned at random (seeded) in proportion to its
#: size: a browser turns a few hundred thousand points smoothly.
MAX_POINTS = 200_000


class Lines(NamedTuple):
    """Line segments drawn as one trace: ``name`` (its legend entry), ``segments`` (S, 2, 3) end points,
    ``dash`` ("solid", "dash", ...)."""

    name: str
    segments: np.ndarray
    dash: str = "solid"


def page(
    clouds: Sequence[np.ndarray],
    names: Sequence[str],
    *,
    title: str,
    lines: Sequence[Lines] = (),
    max_points: int = MAX_POINTS,
    seed: int = 0,
) -> str:
    """The HTML of one page: each (N_k, 3) cloud of ``clouds`` a trace named by ``names``, together thinned to
    at most ``max_points``, then each of ``lines``; equal axes (the clouds' own proportions)."""
    import plotly.graph_objects as go

    if len(clouds) != len(names):
        raise ValueError(f"{len(clouds)} clouds for {len(names)} names")
    total = max(1, sum(len(c) for c in clouds))
    rng = np.random.default_rng(seed)
    figure = go.Figure()
    for cloud, name in zip(clouds, names):
        cloud = np.asarray(cloud, np.float64)
        quota = min(len(cloud), max(1, int(max_points * len(cloud) / total)))
        shown = cloud[np.sort(rng.choice(len(cloud), quota, replace=False))] if len(cloud) else cloud
        figure.add_trace(
            go.Scatter3d(x=shown[:, 0], y=shown[:, 1], z=shown[:, 2], mode="markers", marker={"size": 1.5}, name=name)
        )
    for line in lines:
        segments = np.asarray(line.segments, np.float64).reshape(-1, 2, 3)
        # Segments as one polyline broken by gaps (None between them).
        x, y, z = ([v for s in segments for v in (s[0, k], s[1, k], None)] for k in range(3))
        figure.add_trace(
            go.Scatter3d(x=x, y=y, z=z, mode="lines", line={"dash": line.dash, "width": 3}, name=line.name)
        )
    figure.update_layout(title=title, scene={"aspectmode": "data"}, legend={"itemsizing": "constant"})
    return figure.to_html(include_plotlyjs=True, full_html=True)


def write(path: str | os.PathLike, html: str) -> str:
    """Writes a page to ``path`` (atomically); returns the path."""
    from dit_jax import io

    io.write_text(path, html)
    return os.fspath(path)
