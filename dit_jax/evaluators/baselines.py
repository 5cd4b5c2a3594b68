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
from collections.abc import Callable

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


def open3d_module():
    try:
        import open3d as o3d
    except ImportError:
        raise ImportError(
            "the baselines need Open3D, which dit-jax installs; its wheels load libusb (Debian: apt-get install libusb-1.0-0)"
        ) from None
    return o3d


def open3d_cloud(points: np.ndarray):
    o3d = open3d_module()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64))
    return cloud


def _split(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    transform = np.asarray(transform)
    return transform[:3, :3].astype(np.float64), transform[:3, 3].astype(np.float64)


def features(points: np.ndarray, options: Options):
    """(Open3D cloud, FPFH features) of points (N, 3): downsampled as ``options`` (and :data:`DENSE_POINTS`)
    say, normals and FPFH at the options' radii."""
    o3d = open3d_module()
    cloud = open3d_cloud(points)
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
    o3d = open3d_module()
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
    reg = open3d_module().pipelines.registration
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
    o3d = open3d_module()
    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        open3d_cloud(src),
        open3d_cloud(tgt),
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
    o3d = open3d_module()
    reg = o3d.pipelines.registration
    rotation, translation = ransac_on_features(features(src, options), features(tgt, options), options)
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = rotation, translation
    source, target = open3d_cloud(src), open3d_cloud(tgt)
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
        open3d_module()
    except ImportError:
        return False
    return True
