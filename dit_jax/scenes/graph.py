"""A scene's pose graph: registrations as edges (trusted ones certain, unconfirmed ones uncertain), a spanning
tree that places each scan in its group's frame, doubted links that agree joining groups, and Open3D's
optimisation of each group."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from dit_jax.pipeline.result import Result

#: Two groups join without a trusted registration between them where at least :data:`AGREEING` of the other
#: registrations between them put the one group in the same place beside the other: within these degrees and
#: point spacings (:func:`agreeing_links`). Wrong registrations of low-overlap pairs scatter; right ones agree,
#: and so do wrong ones that a repeated structure explains, which is why a registration whose features saw a
#: rival motion or a turned twin past the verdict's bounds never links (docs/scenes.md).
AGREEING = 2


AGREE_DEGREES = 5.0


AGREE_SPACINGS = 10.0


#: The pose graph's correspondences (its edges' information and the line process) pair points within this
#: many point spacings of the scans (the scene's median spacing, :func:`dit_jax.geometry.neighbours.point_spacing`).
GRAPH_SPACINGS = 3.0


#: An uncertain edge whose line-process weight falls below this is pruned (Open3D's default).
EDGE_PRUNE = 0.25


class Edge(NamedTuple):
    """One registered pair of the scene: ``source`` onto ``target`` (scan indices) by ``result``
    (``result.matrix`` maps the source's points into the target's frame); ``certain`` where the optimisation
    must keep it; ``kept`` where it is in the optimised graph."""

    source: int
    target: int
    result: Result
    certain: bool
    kept: bool = True


def agreeing_links(n_scans: int, edges: Sequence[Edge], others: Sequence[Edge], spacing: float) -> list[Edge]:
    """Of ``others`` (registrations that are no edge), those that join two groups of ``edges`` together with at
    least :data:`AGREEING` - 1 more of them that place the two groups alike (within :data:`AGREE_DEGREES` and
    :data:`AGREE_SPACINGS` point ``spacing``), as uncertain edges."""
    from dit_jax.geometry import rigid

    poses, components = first_poses(n_scans, edges)
    group = {scan: k for k, component in enumerate(components) for scan in component}
    between: dict = {}
    for edge in others:
        a, b = group[edge.source], group[edge.target]
        if a == b or _ambiguous(edge.result):
            continue
        # Group a's frame into group b's, by this registration; stored with the smaller group index first.
        placed = poses[edge.target] @ edge.result.matrix @ np.linalg.inv(poses[edge.source])
        key, placed = ((a, b), placed) if a < b else ((b, a), np.linalg.inv(placed))
        between.setdefault(key, []).append((edge, placed))
    links = []
    for found in between.values():
        best = []
        for _, anchor in found:
            alike = [
                e for e, other in found
                if rigid.rotation_angle_deg(anchor[:3, :3].T @ other[:3, :3]) <= AGREE_DEGREES
                and np.linalg.norm(anchor[:3, 3] - other[:3, 3]) <= AGREE_SPACINGS * spacing
            ]  # fmt: skip
            best = alike if len(alike) > len(best) else best
        if len(best) >= AGREEING:
            links += [e._replace(certain=False, kept=True) for e in best]
    return links


def _ambiguous(result: Result) -> bool:
    """Whether a result's features saw another motion, or a turned twin of it, fit about as well (past the
    verdict's bounds; never for a result found without features)."""
    return bool(result.rival > result.max_rival or result.twin > result.max_twin)  # NaN compares False


def edges_of(pairs: Sequence[tuple[int, int]], results: Sequence[Result]) -> tuple[list[Edge], list[Edge]]:
    """(the graph's edges, the rejected) of registered ``pairs``: a trusted result is a certain edge, an
    unconfirmed one an uncertain edge, a probably wrong one rejected."""
    edges, rejected = [], []
    for (source, target), result in zip(pairs, results):
        edge = Edge(source, target, result, certain=result.level == "trusted")
        if result.level == "probably wrong":
            rejected.append(edge._replace(kept=False))
        else:
            edges.append(edge)
    return edges, rejected


def first_poses(n_scans: int, edges: Sequence[Edge]) -> tuple[np.ndarray, list[list[int]]]:
    """Each scan's pose in its component's frame, along a spanning tree of ``edges`` (the certain ones first,
    then by fitness, Kruskal's order): ((K, 4, 4) poses, components as sorted lists of scan indices, each
    component's frame that of its smallest scan, the largest component first, ties by their first scan)."""
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
        # The tree's poses put the component in the frame of the scan the walk started from: its smallest.
        components.append(sorted(component))
    return poses, sorted(components, key=lambda c: (-len(c), c[0]))


def optimise(
    clouds: Sequence[np.ndarray], poses: np.ndarray, edges: Sequence[Edge], scans: Sequence[int], spacing: float
) -> tuple[np.ndarray, list[Edge]]:
    """Open3D's global optimisation of the pose graph of ``scans`` (a component, its first scan the reference)
    over the ``edges`` between them, from ``poses`` (K, 4, 4), each edge's information from its clouds'
    correspondences within :data:`GRAPH_SPACINGS` times ``spacing``: (the poses with those of ``scans``
    optimised, ``edges`` with ``kept`` as the line process left them)."""
    from dit_jax.features.matching import _o3d

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
