"""Classical registration baselines through Open3D, on the same pairs as DIT.

Each baseline maps ``(src (N, 3), tgt (M, 3))`` to ``(R (3, 3), t (3,))`` with ``tgt ~ R src + t``, for clouds
in the unit sphere (as ModelNet40 and the embedded set are; evaluate.py scales real scans into it):

* ``icp``: point-to-point ICP from the identity (Open3D).
* ``fpfh_ransac``: FPFH features (normals from neighbours within ``normal_radius``, features from those within
  ``feature_radius``), RANSAC on mutual feature matches (3 points, edge-length check 0.9, inlier distance
  ``distance``), optionally on a voxel-downsampled cloud.
* ``fgr``: fast global registration (Zhou et al. 2016) on the same features.
* ``fpfh_ransac_icp`` / ``fgr_icp``: the global estimate refined over every point of both clouds, by one
  tuned :func:`dit_jax.geometry.icp.icp` schedule or by DIT's own refinement (:func:`dit_jax.geometry.icp_refine.refine`), whichever
  scores better on validation pairs of that setting; their time includes both stages.

``room_recipe`` is the other kind: Open3D's global-registration tutorial recipe for rooms in metres, in the
clouds' own units, untuned (5 cm voxel, normals within 2 voxels, FPFH within 5, RANSAC on mutual matches with
1,000,000 draws and inliers within 1.5 voxels, then point-to-plane ICP within 0.4 voxels over every point):
what a 20-line script registers 3DMatch fragments with (:data:`RECIPES`).

Every option is an :class:`Options` field. The defaults are tuned on validation pairs of training shapes
(``python tools/tune_baselines.py``; grid, scores and choice in docs/baselines_tuning.md), per data setting:
:func:`get` with ``setting=`` gives that setting's choice, without one the choice that scores best over all
settings together (for clouds of unknown origin, such as real scans). Clouds far denser than the tuning data
(more than :data:`DENSE_POINTS` points) are voxel-downsampled at :data:`DENSE_VOXEL` before features, as
Open3D's examples do, so FPFH sees the spacing it was tuned for. RANSAC's random parts are seeded
(``open3d.utility.random.seed(0)``) so the figures repeat.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import json
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from dit_jax.geometry import icp as icp_lib
from dit_jax.geometry import icp_refine

NAMES = ("icp", "fpfh_ransac", "fgr", "fpfh_ransac_icp", "fgr_icp")
#: Above this many points a cloud is voxel-downsampled at DENSE_VOXEL (unit-sphere units) for features; the
#: tuning clouds have 205-1024 points, about 0.04 apart.
DENSE_POINTS = 5000
DENSE_VOXEL = 0.025
TUNED_FILE = "baselines_tuned.json"
#: ``Options.icp_method`` that refines as DIT+ICP does (:func:`dit_jax.geometry.icp_refine.refine`).
REFINE = "refine"


@dataclasses.dataclass(frozen=True)
class Options:
    """Every knob of the baselines (unit-sphere units).

    Attributes:
      voxel: voxel size of the downsampling before features; None uses every point.
      normal_radius, normal_neighbours: normals from at most this many neighbours within the radius.
      feature_radius, feature_neighbours: FPFH from at most this many neighbours within the radius.
      distance: RANSAC's inlier distance and FGR's largest correspondence distance.
      ransac_iterations, ransac_confidence: RANSAC's stopping rule.
      icp_distances: the refinement's pairing distances, coarse to fine (see :func:`dit_jax.geometry.icp.icp`), and
        the plain ``icp`` baseline's distance (its first).
      icp_iterations: per refinement stage, and for the plain ``icp`` baseline.
      icp_method: the refinement's "point_to_point" or "point_to_plane" (one ICP with ``icp_distances``), or
        "refine": DIT's own refinement, :func:`dit_jax.geometry.icp_refine.refine` (the best fit among several ICP runs;
        ``icp_distances`` and ``icp_iterations`` unused), so a baseline can be refined exactly as DIT+ICP is.
      fgr_tuple_scale: FGR's tuple test (similarity of the triangles of three matches).
      face_origin: turn the normals to face the cloud's origin before features (a scan's sensor, in its own
        frame); off: as Open3D estimates them.
    """

    normal_radius: float = 0.1
    normal_neighbours: int = 30
    feature_radius: float = 0.25
    feature_neighbours: int = 100
    distance: float = 0.05
    ransac_iterations: int = 100_000
    ransac_confidence: float = 0.999
    icp_distances: tuple[float, ...] = (0.1, 0.05)
    voxel: float | None = None
    icp_iterations: int = 100
    icp_method: str = "point_to_point"
    fgr_tuple_scale: float = 0.95
    face_origin: bool = False

    def replace(self, **changes) -> Options:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> Options:
        values = dict(values)
        if "icp_distances" in values:
            values["icp_distances"] = tuple(values["icp_distances"])
        return cls(**values)


def _o3d():
    try:
        import open3d as o3d
    except ImportError:
        raise ImportError(
            "the baselines need Open3D, which dit-jax installs; its wheels load libusb (Debian: apt-get install libusb-1.0-0)"
        ) from None
    return o3d


def _cloud(points: np.ndarray):
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64))
    return cloud


def _split(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    transform = np.asarray(transform)
    return transform[:3, :3].astype(np.float64), transform[:3, 3].astype(np.float64)


def features(points: np.ndarray, options: Options):
    """(Open3D cloud, FPFH features) of points (N, 3): downsampled as ``options`` (and :data:`DENSE_POINTS`)
    say, normals and FPFH at the options' radii."""
    o3d = _o3d()
    cloud = _cloud(points)
    voxel = options.voxel
    if voxel is None and len(points) > DENSE_POINTS:
        voxel = DENSE_VOXEL
    if voxel:
        cloud = cloud.voxel_down_sample(voxel)
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=options.normal_radius, max_nn=options.normal_neighbours)
    )
    if options.face_origin:
        cloud.orient_normals_towards_camera_location(np.zeros(3))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=options.feature_radius, max_nn=options.feature_neighbours)
    )
    return cloud, fpfh


def ransac_on_features(src_features, tgt_features, options: Options):
    """FPFH + RANSAC on precomputed :func:`features` of both clouds: (R, t)."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(0)
    (s, sf), (t, tf) = src_features, tgt_features
    result = reg.registration_ransac_based_on_feature_matching(
        s,
        t,
        sf,
        tf,
        True,
        options.distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(options.distance)],
        reg.RANSACConvergenceCriteria(options.ransac_iterations, options.ransac_confidence),
    )
    return _split(result.transformation)


def fgr_on_features(src_features, tgt_features, options: Options):
    """Fast global registration on precomputed :func:`features` of both clouds: (R, t)."""
    reg = _o3d().pipelines.registration
    (s, sf), (t, tf) = src_features, tgt_features
    result = reg.registration_fgr_based_on_feature_matching(
        s,
        t,
        sf,
        tf,
        reg.FastGlobalRegistrationOption(
            maximum_correspondence_distance=options.distance, tuple_scale=options.fgr_tuple_scale
        ),
    )
    return _split(result.transformation)


def refine(src: np.ndarray, tgt: np.ndarray, rotation: np.ndarray, translation: np.ndarray, options: Options):
    """A global estimate refined by ICP over every point (``options.icp_method``): (R, t)."""
    if options.icp_method == REFINE:
        result = icp_refine.refine(src, tgt, rotation, translation)
        return result.rotation, result.translation
    result = icp_lib.icp(
        src,
        tgt,
        rotation,
        translation,
        distances=options.icp_distances,
        method=options.icp_method,
        max_iterations=options.icp_iterations,
    )
    return result.rotation, result.translation


def icp(src: np.ndarray, tgt: np.ndarray, options: Options = Options()):
    """Point-to-point ICP from the identity (Open3D), at ``options.icp_distances[0]``."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        _cloud(src),
        _cloud(tgt),
        options.icp_distances[0],
        np.eye(4),
        reg.TransformationEstimationPointToPoint(),
        reg.ICPConvergenceCriteria(max_iteration=options.icp_iterations),
    )
    return _split(result.transformation)


def fpfh_ransac(src: np.ndarray, tgt: np.ndarray, options: Options = Options()):
    return ransac_on_features(features(src, options), features(tgt, options), options)


def fgr(src: np.ndarray, tgt: np.ndarray, options: Options = Options()):
    return fgr_on_features(features(src, options), features(tgt, options), options)


def fpfh_ransac_icp(src: np.ndarray, tgt: np.ndarray, options: Options = Options()):
    return refine(src, tgt, *fpfh_ransac(src, tgt, options), options)


def fgr_icp(src: np.ndarray, tgt: np.ndarray, options: Options = Options()):
    return refine(src, tgt, *fgr(src, tgt, options), options)


_METHODS = {"icp": icp, "fpfh_ransac": fpfh_ransac, "fgr": fgr, "fpfh_ransac_icp": fpfh_ransac_icp, "fgr_icp": fgr_icp}


@functools.lru_cache(maxsize=1)
def tuned() -> dict:
    """The tuned choices shipped with the package: ``{method: {setting or "any": options dict}}`` (empty
    where the file is missing, which leaves every method at :class:`Options` defaults)."""
    path = importlib.resources.files("dit_jax.evaluators") / TUNED_FILE
    if not path.is_file():
        return {}
    return json.loads(path.read_text())["choice"]


def tuned_options(name: str, setting: str | None = None) -> Options:
    """The options ``name`` runs with: the tuned choice for ``setting`` (None or an untuned setting: the
    choice over all settings)."""
    if name not in NAMES:
        raise ValueError(f"unknown baseline {name!r}; choose from {', '.join(NAMES)}")
    choices = tuned().get(name, {})
    chosen = choices.get(setting) if setting is not None else None
    chosen = chosen or choices.get("any")
    return Options.from_dict(chosen) if chosen else Options()


def get(
    name: str, setting: str | None = None, options: Options | None = None
) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The baseline ``name`` as ``(src, tgt) -> (R, t)``, with ``options`` or else its tuned options for
    ``setting`` (see :func:`tuned_options`)."""
    options = options or tuned_options(name, setting)
    return functools.partial(_METHODS[name], options=options)


def room_options(voxel: float = 0.05, *, confidence: float = 0.999, face_origin: bool = False) -> Options:
    """The global stage of Open3D's room recipe (module docs) as :class:`Options`, ``voxel`` in the clouds' units;
    ``confidence``: RANSAC's stopping confidence; ``face_origin``: normals turned to face the sensor."""
    return Options(
        voxel=voxel,
        normal_radius=2 * voxel,
        feature_radius=5 * voxel,
        distance=1.5 * voxel,
        ransac_iterations=1_000_000,
        ransac_confidence=confidence,
        face_origin=face_origin,
    )


def _room(src: np.ndarray, tgt: np.ndarray, options: Options, icp_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC on features at ``options``, then point-to-plane ICP over every point within ``icp_distance``."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    rotation, translation = ransac_on_features(features(src, options), features(tgt, options), options)
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = rotation, translation
    source, target = _cloud(src), _cloud(tgt)
    for cloud in (source, target):
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=options.normal_radius, max_nn=30))
    result = reg.registration_icp(source, target, icp_distance, start, reg.TransformationEstimationPointToPlane())
    return _split(result.transformation)


def room_recipe(src: np.ndarray, tgt: np.ndarray, voxel: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Open3D's tutorial recipe (module docs) on clouds in their own units, ``voxel`` in those units: (R, t)."""
    return _room(src, tgt, room_options(voxel), 0.4 * voxel)


def room_full_strength(src: np.ndarray, tgt: np.ndarray, voxel: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Open3D's room recipe at full strength, ``voxel`` in the clouds' units: normals turned to face the sensor
    (each scan's origin) before FPFH, RANSAC run to confidence 0.9999 (at most 1,000,000 draws), and
    point-to-plane ICP within 0.8 voxels (4 cm at 5 cm), where the tutorial stops at 0.999 and refines within
    0.4 (docs/baselines.md): R, t."""
    return _room(src, tgt, room_options(voxel, confidence=0.9999, face_origin=True), 0.8 * voxel)


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
    0.9999 and point-to-plane ICP within 0.8 voxels (:func:`room_full_strength`, each scan's features computed
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
    o3d = _o3d()
    reg = o3d.pipelines.registration
    options = dataclasses.replace(room_options(voxel, confidence=0.9999, face_origin=True), ransac_iterations=draws)
    found, fine = {}, {}
    for source, target in pairs:
        started = time.perf_counter()
        for k in (source, target):
            if k not in found:
                found[k] = features(clouds[k], options)
                fine[k] = _cloud(clouds[k]).voxel_down_sample(voxel / 2)
                fine[k].estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=options.normal_radius, max_nn=30))
        rotation, translation = ransac_on_features(found[source], found[target], options)
        start = np.eye(4)
        start[:3, :3], start[:3, 3] = rotation, translation
        icp = reg.registration_icp(
            fine[source], fine[target], 0.8 * voxel, start, reg.TransformationEstimationPointToPlane()
        )
        motion = np.asarray(icp.transformation, np.float64)
        info = reg.get_information_matrix_from_point_clouds(fine[source], fine[target], 0.8 * voxel, motion)
        seconds = time.perf_counter() - started
        yield MultiwayPair(source, target, motion, float(icp.fitness), np.asarray(info, np.float64), seconds)


def _multiway_graph(pairs: list[MultiwayPair], voxel: float) -> np.ndarray:
    """:func:`open3d_multiway`'s pose graph from every pair of its K scans (in the order source, then target),
    optimised: the poses (K, 4, 4) into scan 0's frame."""
    o3d = _o3d()
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


#: Baselines at a fixed recipe in the data's own units (metres), not tuned and not scaled into the unit sphere:
#: ``{name: (src, tgt) -> (R, t)}``.
RECIPES = {"open3d_room_5cm": room_recipe, "open3d_room_full": room_full_strength}
#: The registration pipeline's first stage on scans alone (:func:`dit_jax.features.matching.register_both_ways`,
#: as the pipeline calls it, the better fitting direction kept, whatever the verdict): a row the real-scan
#: evaluation can put beside the baselines.
FEATURE_CANDIDATE = "features"
#: Every name the real-scan evaluation takes as a baseline (:mod:`dit_jax.evaluators.scans`).
SCAN_BASELINES = (*NAMES, *RECIPES, FEATURE_CANDIDATE)


def available() -> bool:
    try:
        _o3d()
    except ImportError:
        return False
    return True
