"""A scene from its scans: every scan in one frame, by a pose graph over pairwise registrations.

    from dit_jax import io, registration, scene
    scans = [io.read(p) for p in paths]                  # fragments of one room, each in its camera's frame
    built = scene.register_scene(registration.load(), scans)
    built.poses        # (K, 4, 4): scan k's points into scan 0's frame (where ``built.placed[k]``)
    built.components   # scans that join scan 0 through kept edges, and each group that joins nothing

Unlike a series (:mod:`dit_jax.series`), which needs every link of its chain, a scene registers many pairs
(every pair where the scans are few, else neighbours in the list and pairs whose clouds overlap where the
first estimate places them) and lets the evidence decide:

1. :func:`candidate_pairs`, then each pair registered by the pipeline (:meth:`Registrar.register_pairs`);
2. :func:`edges_of`: a trusted result is a certain edge; any other is an uncertain one, which the optimisation
   may switch off, unless the verdict finds it probably wrong and it lays less than :data:`MIN_FITNESS` of
   its source on the target: that pair is no edge;
3. :func:`first_poses`: a spanning tree of the most trusted edges places each scan it reaches;
4. :func:`optimise`: Open3D's pose-graph optimisation (Levenberg-Marquardt with a line process over the
   uncertain edges, Choi et al. 2015), each edge weighted by the information of its clouds' correspondences.

A scan that no kept edge joins to scan 0 is reported in its own component and left out of the scene, never
forced in.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from dit_jax.result import Result

#: Where a scene has at most this many scans, every pair is registered (K (K - 1) / 2 pairs); above it,
#: neighbours in the list and the pairs :func:`candidate_pairs` finds overlapping.
ALL_PAIRS_SCANS = 40
#: The pose graph's correspondences (its edges' information and the line process) pair points within this
#: many point spacings of the scans (the larger scan's, :func:`dit_jax.icp.point_spacing`).
GRAPH_SPACINGS = 3.0
#: An uncertain edge whose line-process weight falls below this is pruned (Open3D's default).
EDGE_PRUNE = 0.25
#: A result the verdict finds probably wrong still enters the graph, as an uncertain edge, where its fitness
#: (the share of its source it lays on the target) reaches this: on rooms the verdict leaves many right
#: results of low-overlap pairs "probably wrong", and those are what join the scans no trusted result reaches;
#: the line process switches off the ones the rest of the graph contradicts (docs/usage.md, "Scenes").
MIN_FITNESS = 0.5


class Edge(NamedTuple):
    """One registered pair of the scene: ``source`` onto ``target`` (scan indices) by ``result``
    (``result.matrix`` maps the source's points into the target's frame); ``certain`` where the optimisation
    must keep it; ``kept`` where it is in the optimised graph."""

    source: int
    target: int
    result: Result
    certain: bool
    kept: bool = True


@dataclasses.dataclass(frozen=True)
class Scene:
    """Scans in one frame.

    Attributes:
      poses: (K, 4, 4) float64: scan k's points into scan 0's frame, ``x0 = R_k x_k + t_k`` (the identity for a
        scan not placed, see :attr:`placed`).
      edges: every registered pair as an :class:`Edge`, the optimisation's verdict in ``kept``.
      rejected: the registered pairs that entered no graph: the verdict found them probably wrong, and they
        lay less than :data:`MIN_FITNESS` of their source on the target.
      components: lists of scan indices joined by kept edges, scan 0's first.
    """

    poses: np.ndarray
    edges: tuple[Edge, ...]
    rejected: tuple[Edge, ...]
    components: tuple[tuple[int, ...], ...]

    @property
    def placed(self) -> np.ndarray:
        """(K,) bool: the scans joined to scan 0 by kept edges (its component)."""
        placed = np.zeros(len(self.poses), bool)
        placed[list(self.components[0])] = True
        return placed

    def merged(self, clouds: Sequence[np.ndarray], voxel: float | None = None) -> np.ndarray:
        """(N, 3) the placed scans' points in scan 0's frame; with ``voxel``, one point per occupied cell of a
        grid of that size (the first, in the scans' order)."""
        moved = [c @ p[:3, :3].T + p[:3, 3] for c, p, ok in zip(clouds, self.poses, self.placed) if ok]
        points = np.concatenate(moved) if moved else np.zeros((0, 3))
        if voxel is None or len(points) == 0:
            return points
        cells = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        return points[np.sort(first)]

    def plot(self, path, clouds: Sequence[np.ndarray], names: Sequence[str], title: str | None = None) -> str:
        """Writes one self-contained HTML page (:mod:`dit_jax.view`) of the placed scans in scan 0's frame, each
        in its own colour, and the edges between their centres: kept solid, switched off dashed. Returns the
        path."""
        from dit_jax import view

        placed = [k for k in range(len(clouds)) if self.placed[k]]
        moved = [clouds[k] @ self.poses[k][:3, :3].T + self.poses[k][:3, 3] for k in placed]
        centres = {k: m.mean(axis=0) for k, m in zip(placed, moved)}
        lines = []
        for name, kept, dash in (("edges kept", True, "solid"), ("edges switched off", False, "dash")):
            ends = [(centres[e.source], centres[e.target]) for e in self.edges if e.kept == kept and e.source in centres
                    and e.target in centres]  # fmt: skip
            if ends:
                lines.append(view.Lines(name, np.array(ends), dash))
        left_out = len(clouds) - len(placed)
        heading = title or f"{len(placed)} scans placed" + (f", {left_out} left out" if left_out else "")
        return view.write(path, view.page(moved, [names[k] for k in placed], title=heading, lines=lines))

    def to_json(self, names: Sequence[str]) -> dict:
        """The scene as JSON, each scan by its name: poses, placement, components and every edge's verdict."""
        edge = lambda e: {"source": names[e.source], "target": names[e.target], "level": e.result.level,
                          "certain": e.certain, "kept": e.kept, "fitness": e.result.fitness}  # fmt: skip
        return {
            "scans": list(names),
            "poses": self.poses.tolist(),
            "placed": self.placed.tolist(),
            "components": [[names[k] for k in component] for component in self.components],
            "edges": [edge(e) for e in self.edges],
            "rejected": [edge(e) for e in self.rejected],
        }


def pose_lines(poses: np.ndarray, placed: np.ndarray, form: str) -> str:
    """The placed scans' poses (K, 4, 4) as text, a line each: "kitti", the 3 x 4 matrix row by row (KITTI's
    poses.txt); "tum", ``k tx ty tz qx qy qz qw`` with the scan's index k for the time stamp (TUM RGB-D's
    trajectory form)."""
    from scipy.spatial.transform import Rotation

    if form not in ("kitti", "tum"):
        raise ValueError(f"form must be kitti or tum, got {form!r}")
    lines = []
    for k, (pose, ok) in enumerate(zip(poses, placed)):
        if not ok:
            continue
        if form == "kitti":
            lines.append(" ".join(f"{v:.9e}" for v in pose[:3].ravel()))
        else:
            quaternion = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x, y, z, w
            lines.append(" ".join([str(k)] + [f"{v:.9f}" for v in (*pose[:3, 3], *quaternion)]))
    return "\n".join(lines) + "\n"


def candidate_pairs(clouds: Sequence[np.ndarray], poses: np.ndarray | None = None) -> list[tuple[int, int]]:
    """The (source, target) pairs to register among K ``clouds``: every pair (source > target) up to
    :data:`ALL_PAIRS_SCANS` scans; above, each scan onto the one before it, and, given first ``poses``
    (K, 4, 4), every other pair whose bounding spheres overlap where those poses place them."""
    n = len(clouds)
    if n <= ALL_PAIRS_SCANS or poses is None:
        every = [(s, t) for s in range(n) for t in range(s)]
        return every if n <= ALL_PAIRS_SCANS else [(k + 1, k) for k in range(n - 1)]
    centres = np.stack([c.mean(axis=0) for c in clouds])
    radii = np.array([np.linalg.norm(c - m, axis=1).max() for c, m in zip(clouds, centres)])
    placed = np.einsum("kij,kj->ki", poses[:, :3, :3], centres) + poses[:, :3, 3]
    pairs = []
    for s in range(n):
        for t in range(s):
            near = np.linalg.norm(placed[s] - placed[t]) < radii[s] + radii[t]
            if s == t + 1 or near:
                pairs.append((s, t))
    return pairs


def edges_of(pairs: Sequence[tuple[int, int]], results: Sequence[Result]) -> tuple[list[Edge], list[Edge]]:
    """(the graph's edges, the rejected) of registered ``pairs``: a trusted result is a certain edge, the rest
    uncertain ones, but for the "probably wrong" results below :data:`MIN_FITNESS`, which are rejected."""
    edges, rejected = [], []
    for (source, target), result in zip(pairs, results):
        edge = Edge(source, target, result, certain=result.level == "trusted")
        if result.level == "probably wrong" and not result.fitness >= MIN_FITNESS:
            rejected.append(edge._replace(kept=False))
        else:
            edges.append(edge)
    return edges, rejected


def first_poses(n_scans: int, edges: Sequence[Edge]) -> tuple[np.ndarray, list[list[int]]]:
    """Each scan's pose in its component's frame, along a spanning tree of ``edges`` (the certain ones first,
    then by fitness, Kruskal's order): ((K, 4, 4) poses, components as sorted lists of scan indices, each
    component's frame that of its smallest scan, scan 0's component first)."""
    parent = list(range(n_scans))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    tree: dict[int, list[tuple[int, np.ndarray]]] = {k: [] for k in range(n_scans)}
    for edge in sorted(edges, key=lambda e: (not e.certain, -e.result.fitness)):
        a, b = root(edge.source), root(edge.target)
        if a != b:
            parent[a] = b
            motion = edge.result.matrix  # source -> target
            tree[edge.target].append((edge.source, motion))
            tree[edge.source].append((edge.target, np.linalg.inv(motion)))
    poses = np.tile(np.eye(4), (n_scans, 1, 1))
    components, seen = [], set()
    for start in range(n_scans):
        if start in seen:
            continue
        component, stack = [start], [start]
        seen.add(start)
        while stack:
            here = stack.pop()
            for there, motion in tree[here]:  # motion maps ``there`` into ``here``
                if there not in seen:
                    seen.add(there)
                    poses[there] = poses[here] @ motion
                    component.append(there)
                    stack.append(there)
        components.append(sorted(component))
    return poses, components


def optimise(
    clouds: Sequence[np.ndarray], poses: np.ndarray, edges: Sequence[Edge], scans: Sequence[int], spacing: float
) -> tuple[np.ndarray, list[Edge]]:
    """Open3D's global optimisation of the pose graph of ``scans`` (a component, its first scan the reference)
    over the ``edges`` between them, from ``poses`` (K, 4, 4), each edge's information from its clouds'
    correspondences within :data:`GRAPH_SPACINGS` times ``spacing``: (the poses with those of ``scans``
    optimised, ``edges`` with ``kept`` as the line process left them)."""
    from dit_jax.feature_match import _o3d

    o3d = _o3d()
    reg = o3d.pipelines.registration
    distance = GRAPH_SPACINGS * spacing
    node = {scan: k for k, scan in enumerate(scans)}
    thinned = {
        scan: o3d.geometry.PointCloud(
            o3d.utility.Vector3dVector(np.asarray(clouds[scan], np.float64))
        ).voxel_down_sample(spacing)
        for scan in scans
    }
    graph = reg.PoseGraph()
    for scan in scans:
        graph.nodes.append(reg.PoseGraphNode(np.asarray(poses[scan], np.float64)))
    inside = [e for e in edges if e.source in node and e.target in node]
    for edge in inside:
        motion = np.asarray(edge.result.matrix, np.float64)
        info = reg.get_information_matrix_from_point_clouds(
            thinned[edge.source], thinned[edge.target], distance, motion
        )
        graph.edges.append(
            reg.PoseGraphEdge(node[edge.source], node[edge.target], motion, info, uncertain=not edge.certain)
        )
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=distance, edge_prune_threshold=EDGE_PRUNE, reference_node=0
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option
        )
    left = {(scans[e.source_node_id], scans[e.target_node_id]) for e in graph.edges}
    optimised = np.array(poses, np.float64)
    for scan, graph_node in zip(scans, graph.nodes):
        optimised[scan] = np.asarray(graph_node.pose, np.float64)
    return optimised, [edge._replace(kept=(edge.source, edge.target) in left) for edge in inside]


def register_scene(
    registrar,
    clouds: Sequence[np.ndarray],
    *,
    batch_size: int = 8,
    on_pair: Callable[[int], None] | None = None,
) -> Scene:
    """Registers K scans of one scene into scan 0's frame (module docs). ``registrar``: a
    :class:`dit_jax.registration.Registrar`; ``on_pair(count)`` as pairs finish (a progress bar's ``update``)."""
    from dit_jax import icp

    if len(clouds) < 2:
        raise ValueError(f"a scene needs at least 2 scans, got {len(clouds)}")
    pairs = candidate_pairs(clouds)
    results = registrar.register_scan_pairs(clouds, pairs, batch_size=batch_size, on_pair=on_pair)
    edges, rejected = edges_of(pairs, results)
    if len(clouds) > ALL_PAIRS_SCANS:  # neighbours first, then the pairs their chain places overlapping
        poses, _ = first_poses(len(clouds), edges)
        asked = set(pairs)
        more = [p for p in candidate_pairs(clouds, poses) if p not in asked]
        found = registrar.register_scan_pairs(clouds, more, batch_size=batch_size, on_pair=on_pair)
        extra, extra_rejected = edges_of(more, found)
        edges, rejected = edges + extra, rejected + extra_rejected
    spacing = float(np.median([icp.point_spacing(c) for c in clouds]))
    poses, components = first_poses(len(clouds), edges)
    optimised, judged = optimise(clouds, poses, edges, components[0], spacing)
    kept_pairs = {(e.source, e.target) for e in judged if e.kept}
    final_edges = [e._replace(kept=(e.source, e.target) in kept_pairs) for e in edges]
    # Scans the line process cut off from scan 0 leave the scene.
    _, after = first_poses(len(clouds), [e for e in final_edges if e.kept])
    placed = np.isin(np.arange(len(clouds)), after[0])
    poses = np.where(placed[:, None, None], optimised, np.eye(4))
    return Scene(poses, tuple(final_edges), tuple(rejected), tuple(tuple(c) for c in after))
