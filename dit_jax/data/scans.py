"""Real range scans with known poses: a directory of scans and a Stanford ``.conf`` file.

The Stanford 3D Scanning Repository's layout (e.g. the Dragon's turntable series): a ``.conf`` file whose
``bmesh FILE tx ty tz qx qy qz qw`` lines give each scan's pose, ``p_common = R(q)^T p + t`` with ``R(q)`` the
rotation matrix of the unit quaternion (qx, qy, qz, qw), and the scans as PLY files beside it. ``camera`` and
``mesh`` lines are not scans and are skipped.

    scans = load_scans("../shared/data/stanford_dragon_stand")     # in the .conf's order
    for pair in scan_pairs(scans, skip=1):                         # adjacent scans, cyclically
        pair.source, pair.target, pair.rotation, pair.translation  # tgt ~ src @ R.T + t
"""

from __future__ import annotations

import os
import pathlib
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


def quaternion_matrix(q) -> np.ndarray:
    """The rotation matrix (3, 3) of the unit quaternion ``q = (qx, qy, qz, qw)`` (normalised first)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


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


def load_scans(directory: str | os.PathLike) -> list[Scan]:
    """Every scan the directory's ``.conf`` lists, with its pose, in the ``.conf``'s order."""
    conf = find_conf(directory)
    scans = []
    for name, pose in read_conf(conf):
        file = conf.parent / name
        if not file.exists():
            raise DataError(f"{conf}: lists {name}, which is not in {conf.parent}")
        scans.append(Scan(pathlib.Path(name).stem, io.read(file).astype(np.float64), pose))
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
