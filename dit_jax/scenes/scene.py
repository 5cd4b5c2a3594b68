"""A scene from its scans: the scans in one frame, by a pose graph over their pairwise registrations.

    from dit_jax import io, registration
    from dit_jax.scenes import scene
    scans = [io.read(p) for p in paths]                  # fragments of one room, each in its camera's frame
    built = scene.register_scene(registration.load(), scans)
    built.components   # groups of scans joined by trusted registrations, the largest first
    built.poses        # (K, 4, 4): scan k's points into its group's frame (its group's first scan)
    built.placed       # (K,) bool: the scans of the largest group, the scene

Unlike a series (:mod:`dit_jax.scenes.series`), which needs every link of its chain, a scene registers many pairs and
lets the evidence decide:

1. :func:`~dit_jax.scenes.plan.neighbour_pairs`: each scan with the :data:`~dit_jax.scenes.plan.NEIGHBOURS` before it in the list (scans taken along a
   path overlap their neighbours most);
2. :func:`~dit_jax.scenes.graph.edges_of`: a trusted result is an edge; an unconfirmed one an uncertain edge, which the optimisation
   may switch off; a probably wrong one is no edge (on rooms, such results are right too rarely to place a
   scan by);
3. :func:`~dit_jax.scenes.graph.first_poses`: a spanning tree of the edges places each scan in its group's frame; then
   :func:`~dit_jax.scenes.plan.overlap_pairs` (the pairs of one group that the tree lays over each other) and :func:`~dit_jax.scenes.plan.bridge_pairs`
   (scans of different groups a few places apart) are registered and the groups built again, until no new
   pair is left; doubted registrations that agree on how two groups lie join them (:func:`~dit_jax.scenes.graph.agreeing_links`);
4. :func:`~dit_jax.scenes.graph.optimise`: Open3D's pose-graph optimisation of each group (Levenberg-Marquardt with a line process
   over the uncertain edges, Choi et al. 2015), each edge weighted by the information of its clouds'
   correspondences.

Groups that no trusted registration joins stay apart, each in its own frame: the largest is the scene, and
the others are reported, never forced in by a registration the verdict doubts.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from dit_jax.pipeline.result import Result
from dit_jax.scenes import graph, plan

#: Rounds of :func:`~dit_jax.scenes.plan.overlap_pairs` at most (each one's new edges can join groups and lay more scans over
#: each other).
MAX_ROUNDS = 4


@dataclasses.dataclass(frozen=True)
class Scene:
    """Scans in one frame: the largest group of scans that trusted registrations join, and the other groups
    apart, each in its own frame.

    Attributes:
      poses: (K, 4, 4) float64: scan k's points into the frame of its component's first scan,
        ``x_first = R_k x_k + t_k`` (the identity for a scan alone).
      edges: every registered pair the graph holds as an :class:`~dit_jax.scenes.graph.Edge`, the optimisation's verdict in ``kept``.
      rejected: the registered pairs that entered no graph: the verdict found them probably wrong.
      components: sorted tuples of scan indices joined by kept edges, the largest first (ties: the one with
        the earlier scan); ``components[0]`` is the scene.
    """

    poses: np.ndarray
    edges: tuple[graph.Edge, ...]
    rejected: tuple[graph.Edge, ...]
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
    more = plan.neighbour_pairs(len(clouds))
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
        edges, rejected = graph.edges_of(pairs, results)
        links = graph.agreeing_links(len(clouds), edges, rejected, spacing)
        linked = {(e.source, e.target) for e in links}
        edges, rejected = edges + links, [e for e in rejected if (e.source, e.target) not in linked]
        poses, components = graph.first_poses(len(clouds), edges)
        asked = set(pairs)
        more = plan.overlap_pairs(clouds, poses, components, spacing, asked) + plan.bridge_pairs(components, asked)
        if not more:
            break
    judged = []
    for component in components:
        if len(component) > 2:  # two scans' one edge has nothing to agree or disagree with
            poses, kept = graph.optimise(clouds, poses, edges, component, spacing)
            judged += kept
    switched_off = {(e.source, e.target) for e in judged if not e.kept}
    final_edges = [e._replace(kept=(e.source, e.target) not in switched_off) for e in edges]
    # Scans the line process cut off from their component leave it.
    _, after = graph.first_poses(len(clouds), [e for e in final_edges if e.kept])
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
