"""Baselines of whole scenes beside :mod:`dit_jax.scenes`: Open3D's multiway registration (its tutorial's
pairwise ICP, odometry and loop-closure edges, and pose-graph optimisation), in the scans' own units."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from dit_jax.evaluators import baselines

#: Open3D's multiway registration keeps a loop-closure edge where ICP lays at least this share of the source
#: on the target (odometry edges, between neighbours in the list, are always kept).
MULTIWAY_MIN_FITNESS = 0.3


class MultiwayPair(NamedTuple):
    """One registered pair of :func:`open3d_multiway`: scan ``source`` onto scan ``target`` (indices into its
    clouds), ICP's ``motion`` (4, 4), its ``fitness``, the ``information`` (6, 6) of the pair's closest points at
    that motion, and the ``seconds`` its registration took. :meth:`to_record` / :meth:`from_record`: as JSON."""

    source: int
    target: int
    motion: np.ndarray
    fitness: float
    information: np.ndarray
    seconds: float

    def to_record(self) -> dict:
        return {**self._asdict(), "motion": self.motion.tolist(), "information": self.information.tolist()}

    @classmethod
    def from_record(cls, record: dict) -> MultiwayPair:
        arrays = {key: np.asarray(record[key], np.float64) for key in ("motion", "information")}
        return cls(int(record["source"]), int(record["target"]), fitness=float(record["fitness"]),
                   seconds=float(record["seconds"]), **arrays)  # fmt: skip


def open3d_multiway(
    clouds,
    voxel: float = 0.05,
    *,
    draws: int = 1_000_000,
    on_pair: Callable[[int], None] | None = None,
    known: dict[tuple[int, int], MultiwayPair] | None = None,
    on_result: Callable[[MultiwayPair], None] | None = None,
) -> np.ndarray:
    """Open3D's multiway registration of K scans of one scene at full strength, ``voxel`` in their units:
    every pair (source k onto target l > k) by FPFH with normals facing each scan's sensor, RANSAC to confidence
    0.9999 and point-to-plane ICP within 0.8 voxels (:func:`~dit_jax.evaluators.baselines.room_full_strength`, each scan's features computed
    once); odometry edges between neighbours in the list are certain, the other pairs uncertain loop closures
    where ICP's fitness reaches :data:`MULTIWAY_MIN_FITNESS`; then Levenberg-Marquardt with a line process
    (pairing within 1.5 voxels, edges pruned below 0.25), scan 0 the reference. ``draws``: RANSAC's most draws
    a pair (Open3D's multiway tutorial stops at 100,000; most pairs of a scene do not overlap, and there RANSAC
    draws them all). ``known``: pairs registered before, by (source, target), taken as they are (so a stopped
    run resumes); ``on_result(pair)`` as each other pair finishes, ``on_pair(count)`` as pairs finish (known
    ones at once). Returns (K, 4, 4) poses: scan k's points into scan 0's frame."""
    known = dict(known or {})
    wanted = [(s, t) for s in range(len(clouds)) for t in range(s + 1, len(clouds))]
    if on_pair is not None and (reused := sum(pair in known for pair in wanted)):
        on_pair(reused)
    if missing := [pair for pair in wanted if pair not in known]:
        for pair in _multiway_pairs(clouds, voxel, draws, missing):
            known[pair.source, pair.target] = pair
            if on_result is not None:
                on_result(pair)
            if on_pair is not None:
                on_pair(1)
    return _multiway_graph([known[pair] for pair in wanted], voxel)


def _multiway_pairs(clouds, voxel: float, draws: int, pairs: list[tuple[int, int]]):
    """:func:`open3d_multiway`'s registrations of ``pairs`` (source, target) of ``clouds``, one
    :class:`MultiwayPair` at a time (each scan's features computed once, when first needed)."""
    o3d = baselines.open3d_module()
    reg = o3d.pipelines.registration
    options = dataclasses.replace(
        baselines.room_options(voxel, confidence=0.9999, face_origin=True), ransac_iterations=draws
    )
    found, fine = {}, {}
    for source, target in pairs:
        started = time.perf_counter()
        for k in (source, target):
            if k not in found:
                found[k] = baselines.features(clouds[k], options)
                fine[k] = baselines.open3d_cloud(clouds[k]).voxel_down_sample(voxel / 2)
                fine[k].estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=options.normal_radius, max_nn=30))
        rotation, translation = baselines.ransac_on_features(found[source], found[target], options)
        start = np.eye(4)
        start[:3, :3], start[:3, 3] = rotation, translation
        fitted = reg.registration_icp(
            fine[source], fine[target], 0.8 * voxel, start, reg.TransformationEstimationPointToPlane()
        )
        motion = np.asarray(fitted.transformation, np.float64)
        info = reg.get_information_matrix_from_point_clouds(fine[source], fine[target], 0.8 * voxel, motion)
        seconds = time.perf_counter() - started
        yield MultiwayPair(source, target, motion, float(fitted.fitness), np.asarray(info, np.float64), seconds)


def _multiway_graph(pairs: list[MultiwayPair], voxel: float) -> np.ndarray:
    """:func:`open3d_multiway`'s pose graph from every pair of its K scans (in the order source, then target),
    optimised: the poses (K, 4, 4) into scan 0's frame."""
    o3d = baselines.open3d_module()
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odometry))
    for pair in pairs:
        if pair.target == pair.source + 1:
            odometry = pair.motion @ odometry
            graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry)))
            graph.edges.append(
                reg.PoseGraphEdge(pair.source, pair.target, pair.motion, pair.information, uncertain=False)
            )
        elif pair.fitness >= MULTIWAY_MIN_FITNESS:
            graph.edges.append(
                reg.PoseGraphEdge(pair.source, pair.target, pair.motion, pair.information, uncertain=True)
            )
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=1.5 * voxel, edge_prune_threshold=0.25, reference_node=0
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option
        )
    return np.stack([np.asarray(node.pose, np.float64) for node in graph.nodes])


#: Baselines of whole scenes: ``{name: (clouds, on_pair=None, known=None, on_result=None) -> (K, 4, 4) poses in
#: scan 0's frame}`` (as :func:`open3d_multiway`).
SCENE_BASELINES = {"open3d_multiway": open3d_multiway}
