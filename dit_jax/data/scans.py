"""Real range scans with known poses: a directory of scans and a Stanford ``.conf`` file.

The Stanford 3D Scanning Repository's layout (e.g. the Dragon's turntable series): a ``.conf`` file whose
``bmesh FILE tx ty tz qx qy qz qw`` lines give each scan's pose, ``p_common = R(q)^T p + t`` with ``R(q)`` the
rotation matrix of the unit quaternion (qx, qy, qz, qw), and the scans as PLY files beside it. ``camera`` and
``mesh`` lines are not scans and are skipped.

    scans = load_scans("stanford_dragon_stand")                    # scans and their .conf, in its order
    for pair in scan_pairs(scans, skip=1):                         # adjacent scans, cyclically
        pair.source, pair.target, pair.rotation, pair.translation  # tgt ~ src @ R.T + t

:func:`load_pair_sets` reads any of the layouts real benchmarks ship, as named sets of :class:`ScanPair`:

* a Stanford ``.conf`` (above): scan i with scan i + skip, for each skip;
* 3DMatch / 3DLoMatch: fragments ``cloud_bin_<i>.ply`` and a ``gt.log`` (in the folder or in subfolders such
  as ``3DMatch/`` and ``3DLoMatch/``, one set each) whose entries ``i j n`` and a 4 x 4 matrix ``T`` move
  fragment j onto fragment i (``p_i = T p_j``): j is the source. A ``gt.info`` beside it gives each pair's
  information matrix, from which the benchmark's error is computed (:func:`benchmark_rmse`). A folder of
  such scenes (``<scene>/cloud_bin_*.ply``, ``<scene>/3DMatch/gt.log``, ...) gives one set per list, every
  scene's pairs in it, named ``<scene>/cloud_bin_j->cloud_bin_i``;
* KITTI odometry: a ``poses.txt`` of 3 x 4 poses (one line of 12 numbers per scan, the scan's frame to the
  first's) and the scans beside it in name order: scan i with scan i + skip;
* one pair: ``source.*`` and ``target.*`` with ``T_target_source.txt`` (``target ~ T @ source``).

Each set carries the success criterion its benchmark counts with (:data:`CRITERIA`).
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from dit_jax import io
from dit_jax.data.shapes import DataError


class Scan(NamedTuple):
    """One scan in its own (scanner) frame."""

    name: str
    points: np.ndarray  # (N, 3) float64
    pose: np.ndarray  # (4, 4): homogeneous map from the scan's frame to the common frame


class ScanPair(NamedTuple):
    """Two scans and the true motion registering the source onto the target: ``tgt ~ src @ R.T + t``."""

    name: str
    source: np.ndarray  # (N, 3)
    target: np.ndarray  # (M, 3)
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    info: np.ndarray | None = None  # (6, 6) the 3DMatch benchmark's information matrix, where it gives one
    scene: str = ""  # the scene a benchmark's pair comes from ("" where the set has one)
    consecutive: bool = False  # fragments next to each other in their scan: the 3DMatch benchmark skips them


def quaternion_matrix(q) -> np.ndarray:
    """The rotation matrix (3, 3) of the unit quaternion ``q = (qx, qy, qz, qw)`` (normalised first)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, np.float64)).as_matrix()


def read_conf(path: str | os.PathLike) -> list[tuple[str, np.ndarray]]:
    """The ``bmesh`` lines of a Stanford ``.conf``: ``[(file name, pose (4, 4)), ...]`` in file order."""
    poses = []
    for number, line in enumerate(pathlib.Path(path).read_text().splitlines(), 1):
        fields = line.split()
        if not fields or fields[0] != "bmesh":
            continue
        if len(fields) != 9:
            raise DataError(f"{path}:{number}: expected 'bmesh FILE tx ty tz qx qy qz qw', got {line.strip()!r}")
        try:
            t, q = np.array(fields[2:5], np.float64), np.array(fields[5:9], np.float64)
        except ValueError:
            raise DataError(f"{path}:{number}: non-numeric pose in {line.strip()!r}") from None
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = quaternion_matrix(q).T, t  # the transpose: see the module docs
        poses.append((fields[1], pose))
    if not poses:
        raise DataError(f"{path}: no 'bmesh' lines (expected a Stanford .conf of range scans)")
    return poses


def find_conf(directory: str | os.PathLike) -> pathlib.Path:
    """The single ``.conf`` file of a scan directory."""
    path = pathlib.Path(directory)
    if not path.is_dir():
        raise DataError(f"{path}: no such directory (expected range scans with a Stanford .conf)")
    confs = sorted(path.glob("*.conf"))
    if len(confs) != 1:
        raise DataError(f"{path}: expected one .conf file with the scans' poses, found {len(confs)}")
    return confs[0]


def _read_scan(file: pathlib.Path, listed_in: pathlib.Path) -> np.ndarray:
    if not file.exists():
        raise DataError(f"{listed_in}: lists {file.name}, which is not in {file.parent}")
    return io.read(file).astype(np.float64)


def load_scans(directory: str | os.PathLike) -> list[Scan]:
    """Every scan the directory's ``.conf`` lists, with its pose, in the ``.conf``'s order."""
    conf = find_conf(directory)
    scans = []
    for name, pose in read_conf(conf):
        scans.append(Scan(pathlib.Path(name).stem, _read_scan(conf.parent / name, conf), pose))
    return scans


def relative_motion(source: Scan, target: Scan) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) registering ``source`` onto ``target``: ``inv(T_target) @ T_source``."""
    motion = np.linalg.inv(target.pose) @ source.pose
    return motion[:3, :3], motion[:3, 3]


def scan_pairs(scans: list[Scan], skip: int = 1) -> list[ScanPair]:
    """Pairs of scan i and scan i + ``skip``, cyclically (a turntable series closes on itself): as many pairs
    as scans. ``skip=1`` gives adjacent scans, ``skip=2`` every second one."""
    if not 1 <= skip < len(scans):
        raise ValueError(f"skip must be in 1..{len(scans) - 1}, got {skip}")
    out = []
    for i, source in enumerate(scans):
        target = scans[(i + skip) % len(scans)]
        rotation, translation = relative_motion(source, target)
        out.append(ScanPair(f"{source.name}->{target.name}", source.points, target.points, rotation, translation))
    return out


#: What each kind of data counts as registered: (degrees, units of the data) of rotation and translation
#: error, as its benchmark counts (3DMatch / 3DLoMatch: 15 degrees and 0.3 m; KITTI and LiDAR pairs: 5 degrees
#: and 2 m); None where the data says nothing of scale (a turntable series of an object).
CRITERIA = {"conf": None, "gt.log": (15.0, 0.3), "kitti": (5.0, 2.0), "pair": (5.0, 2.0)}


class PairSet(NamedTuple):
    """Named pairs of one benchmark list, and what it counts as registered (``(degrees, distance)`` or None)."""

    pairs: list[ScanPair]
    criterion: tuple[float, float] | None
    kind: str  # a key of CRITERIA


def _read_pair_matrices(path: str | os.PathLike, size: int, what: str) -> list[tuple[int, int, np.ndarray]]:
    """The entries of a 3DMatch log of pairs: each a header line ``i j n`` and a ``size`` x ``size`` matrix
    (``what`` names it in errors)."""
    lines = [line.split() for line in pathlib.Path(path).read_text().splitlines() if line.strip()]
    rows = size + 1
    if len(lines) % rows:
        raise DataError(
            f"{path}: expected entries of {rows} lines ('i j n', then the {size} rows of {what}), "
            f"found {len(lines)} lines"
        )
    entries = []
    for k in range(0, len(lines), rows):
        try:
            i, j = int(lines[k][0]), int(lines[k][1])
            matrix = np.array(lines[k + 1 : k + rows], np.float64)
        except (ValueError, IndexError):
            matrix = None
        if matrix is None or matrix.shape != (size, size):
            raise DataError(f"{path}: entry {k // rows + 1} is not 'i j n' and {what} ({size} x {size})")
        entries.append((i, j, matrix))
    return entries


def read_gt_log(path: str | os.PathLike) -> list[tuple[int, int, np.ndarray]]:
    """The entries of a 3DMatch ``gt.log``: ``[(i, j, T (4, 4)), ...]``, ``T`` moving fragment j onto i."""
    return _read_pair_matrices(path, 4, "a motion T")


def read_gt_info(path: str | os.PathLike) -> dict[tuple[int, int], np.ndarray]:
    """The entries of a 3DMatch ``gt.info``: ``{(i, j): Sigma (6, 6)}``, the information matrix of the pair
    whose ``gt.log`` entry is ``i j``."""
    return {(i, j): matrix for i, j, matrix in _read_pair_matrices(path, 6, "an information matrix")}


def scene_poses(scene_dir: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The true pose of every fragment of a 3DMatch scene folder, chained from the ``gt.log`` of both its lists
    (3DMatch and 3DLoMatch; either alone leaves some fragments of some scenes unconnected): ((K, 4, 4) fragment
    k's points into fragment 0's frame, (K,) bool whether the lists join fragment k to fragment 0 at all; the
    identity where they do not, as mit_lab's fragment 12, in no pair of either list)."""
    directory = pathlib.Path(scene_dir)
    links: dict[int, list[tuple[int, np.ndarray]]] = {}
    count = 0
    for log in sorted(directory.glob("*/gt.log")):
        for i, j, motion in read_gt_log(log):  # motion: fragment j into fragment i's frame
            links.setdefault(i, []).append((j, motion))
            links.setdefault(j, []).append((i, np.linalg.inv(motion)))
            count = max(count, i + 1, j + 1)
    count = max(count, len(list(directory.glob("cloud_bin_*.*"))))
    poses = np.full((count, 4, 4), np.nan)
    poses[0], stack = np.eye(4), [0]
    while stack:
        here = stack.pop()
        for there, motion in links.get(here, []):
            if np.isnan(poses[there, 0, 0]):
                poses[there] = poses[here] @ motion
                stack.append(there)
    known = ~np.isnan(poses[:, 0, 0])
    poses[~known] = np.eye(4)
    return poses, known


#: The 3DMatch benchmark's registration threshold: an RMSE of the true correspondences of 0.2 m.
BENCHMARK_RMSE = 0.2


def benchmark_rmse(rotation: np.ndarray, translation: np.ndarray, pair: ScanPair) -> float:
    """The 3DMatch benchmark's error of an estimate ``tgt ~ src @ R.T + t`` of ``pair`` (Choi et al., "Robust
    Reconstruction of Indoor Scenes", CVPR 2015, as 3DMatch and PREDATOR score it): with ``E = inv(T_true)
    T_est`` and ``xi`` its translation and the vector part of its rotation's unit quaternion, ``sqrt(xi' Sigma
    xi / Sigma[0, 0])``, about the RMSE of the pair's true correspondences in the data's units. A pair is
    registered at :data:`BENCHMARK_RMSE` or less. NaN where the pair has no information matrix, or an empty
    one: 3DLoMatch's own ``gt.info`` holds one (home_md, fragments 23 and 25), which the benchmark's code counts
    as not registered whatever the estimate, and so does :mod:`dit_jax.evaluators.scans`."""
    if pair.info is None or not pair.info[0, 0] > 0:
        return float("nan")
    truth, estimate = np.eye(4), np.eye(4)
    truth[:3, :3], truth[:3, 3] = pair.rotation, pair.translation
    estimate[:3, :3], estimate[:3, 3] = rotation, translation
    error = np.linalg.inv(truth) @ estimate
    # The vector part of the error rotation's unit quaternion (its sign does not change the quadratic form).
    from scipy.spatial.transform import Rotation

    vector = Rotation.from_matrix(error[:3, :3]).as_quat(canonical=True)[:3]
    xi = np.concatenate([error[:3, 3], vector])
    return float(np.sqrt(max(0.0, xi @ pair.info @ xi / pair.info[0, 0])))


def _pair(name: str, source: np.ndarray, target: np.ndarray, motion: np.ndarray, **fields) -> ScanPair:
    return ScanPair(name, source, target, motion[:3, :3], motion[:3, 3], **fields)


def _gt_log_sets(directory: pathlib.Path, logs: list[pathlib.Path], scene: str = "") -> dict[str, PairSet]:
    cache: dict[pathlib.Path, np.ndarray] = {}

    def fragment(index: int, log: pathlib.Path) -> np.ndarray:
        for folder in (log.parent, directory):
            candidates = sorted(folder.glob(f"cloud_bin_{index}.*"))
            if candidates:
                if candidates[0] not in cache:
                    cache[candidates[0]] = _read_scan(candidates[0], log)
                return cache[candidates[0]]
        raise DataError(f"{log}: lists fragment {index}, but no cloud_bin_{index}.* is in {directory}")

    sets = {}
    prefix = f"{scene}/" if scene else ""
    for log in logs:
        name = log.parent.name if log.parent != directory else directory.name
        info_file = log.with_name("gt.info")
        info = read_gt_info(info_file) if info_file.exists() else {}
        pairs = [
            _pair(
                f"{prefix}cloud_bin_{j}->cloud_bin_{i}",
                fragment(j, log),
                fragment(i, log),
                matrix,
                info=info.get((i, j)),
                scene=scene,
                consecutive=abs(j - i) <= 1,
            )
            for i, j, matrix in read_gt_log(log)
        ]
        sets[name] = PairSet(pairs, CRITERIA["gt.log"], "gt.log")
    return sets


def _scene_sets(directory: pathlib.Path, scenes: list[pathlib.Path]) -> dict[str, PairSet]:
    """One set per list name (``3DMatch``, ``3DLoMatch``), every scene's pairs in it, scene by scene."""
    merged: dict[str, list[ScanPair]] = {}
    for scene in scenes:
        logs = sorted(scene.glob("gt.log")) + sorted(scene.glob("*/gt.log"))
        for name, found in _gt_log_sets(scene, logs, scene.name).items():
            merged.setdefault(scene.name if name == scene.name else name, []).extend(found.pairs)
    return {name: PairSet(pairs, CRITERIA["gt.log"], "gt.log") for name, pairs in merged.items()}


def _kitti_set(poses_file: pathlib.Path, skips: Sequence[int]) -> dict[str, PairSet]:
    try:
        poses = np.loadtxt(poses_file, ndmin=2)
    except ValueError:
        raise DataError(f"{poses_file}: expected one line of 12 numbers (a 3 x 4 pose) per scan") from None
    if poses.shape[1] != 12:
        raise DataError(f"{poses_file}: expected one line of 12 numbers (a 3 x 4 pose) per scan")
    files = sorted(
        f for f in poses_file.parent.iterdir() if f.suffix.lower() in io.READ_FORMATS and f.name != poses_file.name
    )
    if len(files) != len(poses):
        raise DataError(f"{poses_file}: {len(poses)} poses for {len(files)} scans in {poses_file.parent}")
    pose = [np.vstack([row.reshape(3, 4), [0, 0, 0, 1]]) for row in poses]
    points = [_read_scan(f, poses_file) for f in files]
    sets = {}
    for skip in skips:
        pairs = [
            _pair(
                f"{files[i].stem}->{files[i + skip].stem}",
                points[i],
                points[i + skip],
                np.linalg.inv(pose[i + skip]) @ pose[i],
            )
            for i in range(len(files) - skip)
        ]
        sets[f"skip{skip}"] = PairSet(pairs, CRITERIA["kitti"], "kitti")
    return sets


def load_pair_sets(directory: str | os.PathLike, skips: Sequence[int] = (1, 2)) -> dict[str, PairSet]:
    """The named pair sets of a folder of real scans in any layout of the module docs (``skips`` for series:
    a ``.conf`` or KITTI ``poses.txt``)."""
    path = pathlib.Path(directory)
    if not path.is_dir():
        raise DataError(f"{path}: no such directory")
    if sorted(path.glob("*.conf")):
        series = load_scans(path)
        return {f"skip{k}": PairSet(scan_pairs(series, k), CRITERIA["conf"], "conf") for k in skips}
    logs = sorted(path.glob("gt.log")) + sorted(path.glob("*/gt.log"))
    if logs and any(path.glob("cloud_bin_*")):
        return _gt_log_sets(path, logs)
    scenes = sorted({log.parents[1] for log in path.glob("*/*/gt.log")} | {log.parent for log in logs})
    if scenes:
        return _scene_sets(path, scenes)
    if (path / "poses.txt").exists():
        return _kitti_set(path / "poses.txt", skips)
    if (path / "T_target_source.txt").exists():
        try:
            motion = np.loadtxt(path / "T_target_source.txt")
        except ValueError:
            motion = None
        if motion is None or motion.shape != (4, 4):
            raise DataError(f"{path / 'T_target_source.txt'}: expected a 4 x 4 matrix")
        found = {
            role: sorted(f for f in path.glob(f"{role}.*") if f.suffix.lower() in io.READ_FORMATS)
            for role in ("source", "target")
        }
        if not found["source"] or not found["target"]:
            raise DataError(f"{path}: T_target_source.txt needs a source.* and a target.* cloud beside it")
        pair = _pair(path.name, _read_scan(found["source"][0], path), _read_scan(found["target"][0], path), motion)
        return {"pair": PairSet([pair], CRITERIA["pair"], "pair")}
    raise DataError(
        f"{path}: no scan poses found (a Stanford .conf, a 3DMatch gt.log, a KITTI poses.txt, or T_target_source.txt)"
    )
