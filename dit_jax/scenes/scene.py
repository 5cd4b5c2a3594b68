"""A scene from its scans: the scans in one frame, by a pose graph over their pairwise registrations.

    from dit_jax import io, registration, scene
    scans = [io.read(p) for p in paths]                  # fragments of one room, each in its camera's frame
    built = scene.register_scene(registration.load(), scans)
    built.components   # groups of scans joined by trusted registrations, the largest first
    built.poses        # (K, 4, 4): scan k's points into its group's frame (its group's first scan)
    built.placed       # (K,) bool: the scans of the largest group, the scene

Unlike a series (:mod:`dit_jax.scenes.series`), which needs every link of its chain, a scene registers many pairs and
lets the evidence decide:

1. :func:`neighbour_pairs`: each scan with the :data:`NEIGHBOURS` before it in the list (scans taken along a
   path overlap their neighbours most);
2. :func:`edges_of`: a trusted result is an edge; an unconfirmed one an uncertain edge, which the optimisation
   may switch off; a probably wrong one is no edge (on rooms, such results are right too rarely to place a
   scan by);
3. :func:`first_poses`: a spanning tree of the edges places each scan in its group's frame; then
   :func:`overlap_pairs` (the pairs of one group that the tree lays over each other) and :func:`bridge_pairs`
   (scans of different groups a few places apart) are registered and the groups built again, until no new
   pair is left; doubted registrations that agree on how two groups lie join them (:func:`agreeing_links`);
4. :func:`optimise`: Open3D's pose-graph optimisation of each group (Levenberg-Marquardt with a line process
   over the uncertain edges, Choi et al. 2015), each edge weighted by the information of its clouds'
   correspondences.

Groups that no trusted registration joins stay apart, each in its own frame: the largest is the scene, and
the others are reported, never forced in by a registration the verdict doubts.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np

from dit_jax.pipeline.result import Result

#: Each scan is registered onto this many scans before it in the list: the neighbours along a camera's path.
#: With the overlap rounds after them, they reach the groups that registering every pair reaches, for far
#: fewer pairs (docs/scenes.md).
NEIGHBOURS = 3
#: Scans of different groups are registered where they lie at most this many places apart in the list
#: (:func:`bridge_pairs`): where the path broke, the scans a few steps on may still join the groups.
BRIDGE_NEIGHBOURS = 8
#: Two groups join without a trusted registration between them where at least :data:`AGREEING` of the other
#: registrations between them put the one group in the same place beside the other: within these degrees and
#: point spacings (:func:`agreeing_links`). Wrong registrations of low-overlap pairs scatter; right ones agree,
#: and so do wrong ones that a repeated structure explains, which is why a registration whose features saw a
#: rival motion or a turned twin past the verdict's bounds never links (docs/scenes.md).
AGREEING = 2
AGREE_DEGREES = 5.0
AGREE_SPACINGS = 10.0
#: :func:`overlap_pairs` lays the scans on a grid of cells this many point spacings wide, and registers two
#: scans of one group where their shared cells are at least :data:`MIN_SHARED_CELLS` of the smaller one's.
OVERLAP_CELL_SPACINGS = 10.0
MIN_SHARED_CELLS = 0.2
#: Rounds of :func:`overlap_pairs` at most (each one's new edges can join groups and lay more scans over
#: each other).
MAX_ROUNDS = 4
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


@dataclasses.dataclass(frozen=True)
class Scene:
    """Scans in one frame: the largest group of scans that trusted registrations join, and the other groups
    apart, each in its own frame.

    Attributes:
      poses: (K, 4, 4) float64: scan k's points into the frame of its component's first scan,
        ``x_first = R_k x_k + t_k`` (the identity for a scan alone).
      edges: every registered pair the graph holds as an :class:`Edge`, the optimisation's verdict in ``kept``.
      rejected: the registered pairs that entered no graph: the verdict found them probably wrong.
      components: sorted tuples of scan indices joined by kept edges, the largest first (ties: the one with
        the earlier scan); ``components[0]`` is the scene.
    """

    poses: np.ndarray
    edges: tuple[Edge, ...]
    rejected: tuple[Edge, ...]
    components: tuple[tuple[int, ...], ...]

    @property
    def placed(self) -> np.ndarray:
        """(K,) bool: the scans of the scene (the largest component)."""
        placed = np.zeros(len(self.poses), bool)
        placed[list(self.components[0])] = True
        return placed

    @property
    def frame(self) -> int:
        """The scan whose frame the scene's poses are in: the first of the largest component."""
        return self.components[0][0]

    def component_of(self, scan: int) -> int:
        """The index into :attr:`components` of the one holding ``scan``."""
        return next(k for k, component in enumerate(self.components) if scan in component)

    def merged(self, clouds: Sequence[np.ndarray], voxel: float | None = None) -> np.ndarray:
        """(N, 3) the placed scans' points in the scene's frame (:attr:`frame`); with ``voxel``, one point per occupied cell of a
        grid of that size (the first, in the scans' order)."""
        moved = [c @ p[:3, :3].T + p[:3, 3] for c, p, ok in zip(clouds, self.poses, self.placed) if ok]
        points = np.concatenate(moved) if moved else np.zeros((0, 3))
        if voxel is None or len(points) == 0:
            return points
        cells = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        return points[np.sort(first)]

    def plot(self, path, clouds: Sequence[np.ndarray], names: Sequence[str], title: str | None = None) -> str:
        """Writes one self-contained HTML page (:mod:`dit_jax.pictures.view`) of the placed scans in the scene's frame, each
        in its own colour, and the edges between their centres: kept solid, switched off dashed; or, for a path
        ending in .png, a picture of them from two sides (:func:`dit_jax.pictures.plotting.plot_series`). Returns the
        path."""
        from dit_jax.pictures import view

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
        if str(path).lower().endswith(".png"):
            from dit_jax.pictures import plotting

            return plotting.plot_series(path, moved, names=[names[k] for k in placed], title=heading)
        return view.write(path, view.page(moved, [names[k] for k in placed], title=heading, lines=lines))

    def to_json(self, names: Sequence[str]) -> dict:
        """The scene as JSON, each scan by its name: its frame, each scan's pose in its component's frame and
        its component, the components and every edge's verdict."""
        edge = lambda e: {"source": names[e.source], "target": names[e.target], "level": e.result.level,
                          "certain": e.certain, "kept": e.kept, "fitness": e.result.fitness}  # fmt: skip
        return {
            "scans": list(names),
            "frame": names[self.frame],
            "poses": self.poses.tolist(),
            "placed": self.placed.tolist(),
            "component": [self.component_of(k) for k in range(len(names))],
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


def register_scene(
    registrar,
    clouds: Sequence[np.ndarray],
    *,
    batch_size: int = 8,
    on_pair: Callable[[int], None] | None = None,
    on_planned: Callable[[int], None] | None = None,
    known: Mapping[tuple[int, int], Result] | None = None,
    on_result: Callable[[tuple[int, int], Result], None] | None = None,
) -> Scene:
    """Registers K scans of one scene into the frame of the first scan of their largest component (module
    docs). ``registrar``: a :class:`dit_jax.pipeline.registration.Registrar`; ``on_pair(count)`` as pairs finish (a
    progress bar's ``update``); ``on_planned(count)`` as pairs join the plan (the neighbours, then each round's
    overlapping pairs).

    Resuming: ``known`` maps pairs ``(source, target)`` registered before (an earlier run's results, e.g. read
    back by :meth:`Result.from_record`) to their results, which are taken as they are; ``on_result(pair,
    result)`` is called as each newly registered batch finishes (to append it to a results file), so a run
    killed part way loses at most one batch. The plan follows the results, so a resumed run plans the same
    pairs and builds the same scene."""
    if len(clouds) < 2:
        raise ValueError(f"a scene needs at least 2 scans, got {len(clouds)}")
    scans = registrar.prepare_scans(clouds)
    spacing = float(np.median(scans.spacings))
    known = dict(known or {})
    pairs, results = [], []
    more = neighbour_pairs(len(clouds))
    for _ in range(MAX_ROUNDS + 1):
        if on_planned is not None:
            on_planned(len(more))
        if on_pair is not None and (reused := sum(pair in known for pair in more)):
            on_pair(reused)
        new = [pair for pair in more if pair not in known]
        for start in range(0, len(new), batch_size):
            batch = new[start : start + batch_size]
            found = registrar.register_scan_pairs(scans, batch, batch_size=batch_size, on_pair=on_pair)
            for pair, result in zip(batch, found):
                known[pair] = result
                if on_result is not None:
                    on_result(pair, result)
        results += [known[pair] for pair in more]
        pairs += more
        edges, rejected = edges_of(pairs, results)
        links = agreeing_links(len(clouds), edges, rejected, spacing)
        linked = {(e.source, e.target) for e in links}
        edges, rejected = edges + links, [e for e in rejected if (e.source, e.target) not in linked]
        poses, components = first_poses(len(clouds), edges)
        asked = set(pairs)
        more = overlap_pairs(clouds, poses, components, spacing, asked) + bridge_pairs(components, asked)
        if not more:
            break
    judged = []
    for component in components:
        if len(component) > 2:  # two scans' one edge has nothing to agree or disagree with
            poses, kept = optimise(clouds, poses, edges, component, spacing)
            judged += kept
    switched_off = {(e.source, e.target) for e in judged if not e.kept}
    final_edges = [e._replace(kept=(e.source, e.target) not in switched_off) for e in edges]
    # Scans the line process cut off from their component leave it.
    _, after = first_poses(len(clouds), [e for e in final_edges if e.kept])
    return Scene(_in_component_frames(poses, after), tuple(final_edges), tuple(rejected), tuple(map(tuple, after)))


def progress(bar) -> dict:
    """:func:`register_scene`'s ``on_pair`` and ``on_planned`` for a tqdm ``bar`` whose total grows with the plan
    (none for None)."""
    if bar is None:
        return {}

    def planned(count: int) -> None:
        bar.total += count
        bar.refresh()

    return {"on_pair": bar.update, "on_planned": planned}


def _in_component_frames(poses: np.ndarray, components: Sequence[Sequence[int]]) -> np.ndarray:
    """``poses`` (K, 4, 4) moved so that each component's first scan has the identity (a scan alone: the
    identity)."""
    moved = np.array(poses, np.float64)
    for component in components:
        moved[list(component)] = np.linalg.inv(poses[component[0]]) @ poses[list(component)]
    return moved
