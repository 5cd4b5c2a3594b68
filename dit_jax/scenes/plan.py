"""Which pairs of a scene's scans to register: each scan with its neighbours in the list, then the pairs a first
placement lays over each other, then scans of different groups a few places apart."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Each scan is registered onto this many scans before it in the list: the neighbours along a camera's path.
#: With the overlap rounds after them, they reach the groups that registering every pair reaches, for far
#: fewer pairs (docs/scenes.md).
NEIGHBOURS = 3


#: Scans of different groups are registered where they lie at most this many places apart in the list
#: (:func:`bridge_pairs`): where the path broke, the scans a few steps on may still join the groups.
BRIDGE_NEIGHBOURS = 8


#: :func:`overlap_pairs` lays the scans on a grid of cells this many point spacings wide, and registers two
#: scans of one group where their shared cells are at least :data:`MIN_SHARED_CELLS` of the smaller one's.
OVERLAP_CELL_SPACINGS = 10.0


MIN_SHARED_CELLS = 0.2


def neighbour_pairs(n_scans: int) -> list[tuple[int, int]]:
    """The first pairs a scene registers: each scan (source) onto the :data:`NEIGHBOURS` before it (target)."""
    return [(s, t) for s in range(n_scans) for t in range(max(0, s - NEIGHBOURS), s)]


def overlap_pairs(
    clouds: Sequence[np.ndarray],
    poses: np.ndarray,
    components: Sequence[Sequence[int]],
    spacing: float,
    asked: set,
) -> list[tuple[int, int]]:
    """The pairs (source > target) of one component, not in ``asked``, whose scans ``poses`` (K, 4, 4) lay over
    each other: on a grid of :data:`OVERLAP_CELL_SPACINGS` point ``spacing`` cells, their shared cells are at
    least :data:`MIN_SHARED_CELLS` of the smaller one's (each scan measured on about 5,000 of its points)."""
    cell = OVERLAP_CELL_SPACINGS * spacing
    cells = []
    for cloud, pose in zip(clouds, poses):
        points = np.asarray(cloud[:: max(1, len(cloud) // 5_000)], np.float64) @ pose[:3, :3].T + pose[:3, 3]
        cells.append(np.unique(np.floor(points / cell).astype(np.int64), axis=0))
    key = lambda c: np.ascontiguousarray(c).view([("", c.dtype)] * 3).ravel()  # noqa: E731  a cell as one value
    pairs = []
    for component in components:
        for s in component:
            for t in component:
                if t < s and (s, t) not in asked:
                    shared = len(np.intersect1d(key(cells[s]), key(cells[t])))
                    if shared >= MIN_SHARED_CELLS * min(len(cells[s]), len(cells[t])):
                        pairs.append((s, t))
    return pairs


def bridge_pairs(components: Sequence[Sequence[int]], asked: set) -> list[tuple[int, int]]:
    """The pairs (source > target), not in ``asked``, of scans in different ``components`` at most
    :data:`BRIDGE_NEIGHBOURS` places apart in the list."""
    group = {scan: k for k, component in enumerate(components) for scan in component}
    return [
        (s, t) for s in sorted(group) for t in range(max(0, s - BRIDGE_NEIGHBOURS), s)
        if group[s] != group[t] and (s, t) not in asked
    ]  # fmt: skip
