"""PCD files (pypcd4): read, written, moved with their sensor's viewpoint."""

from __future__ import annotations

import io as io_lib
import struct

import numpy as np

from dit_jax.io.common import _NORMALS, _XYZ, CloudFileError, _columns, _first_line, _move_fields


def _pcd(path: str):
    """The ``pypcd4.PointCloud`` of a PCD file (any of its three encodings)."""
    from pypcd4 import PointCloud

    try:
        return PointCloud.from_path(path)
    except (ValueError, KeyError, IndexError, TypeError, EOFError, RuntimeError, struct.error) as err:
        raise CloudFileError(path, f"malformed PCD file ({_first_line(err)})") from None


def _read_pcd(path: str, select) -> tuple[np.ndarray, int]:
    cloud = _pcd(path)
    _columns(path, list(cloud.fields))
    data = cloud.pc_data
    header = cloud.metadata
    if len(data) != header.points or header.width * header.height != header.points:
        raise CloudFileError(
            path,
            f"its header says POINTS {header.points:,} (WIDTH {header.width:,} x HEIGHT {header.height:,}) "
            f"but it holds {len(data):,}",
        )
    rows_kept = select(len(data))
    kept = data if rows_kept is None else data[rows_kept]
    return np.stack([np.asarray(kept[axis], np.float64) for axis in _XYZ], axis=1), len(data)


def _moved_pcd(path: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of PCD file ``path`` (pypcd4) with x, y, z moved, normal_x, normal_y, normal_z turned and the
    VIEWPOINT (the sensor's pose in the cloud's frame) moved with the points; other fields kept, ASCII written
    as ASCII and binary (compressed or not) as binary."""
    from pypcd4 import Encoding

    cloud = _pcd(path)
    _columns(path, list(cloud.fields))
    meta = cloud.metadata
    if any(meta.type[meta.fields.index(axis)] != "F" for axis in _XYZ):
        raise CloudFileError(
            path,
            "PCD coordinates stored as integers would be rounded when moved; "
            "write the moved points to another file instead",
        )
    data = np.array(cloud.pc_data)  # a writable copy
    _move_fields(data, _NORMALS[".pcd"], rotation, translation)
    from scipy.spatial.transform import Rotation

    view = np.asarray(meta.viewpoint, np.float64)  # tx ty tz qw qx qy qz
    turned = Rotation.from_matrix(rotation) * Rotation.from_quat(view[3:], scalar_first=True)
    pose = (*(rotation @ view[:3] + translation), *turned.as_quat(canonical=True, scalar_first=True))
    moved = type(cloud)(meta.model_copy(update={"viewpoint": tuple(float(v) for v in pose)}), data)
    buffer = io_lib.BytesIO()
    moved.save(buffer, encoding=Encoding.ASCII if meta.data == Encoding.ASCII else Encoding.BINARY)
    return buffer.getvalue()


def _write_pcd(f, points: np.ndarray, binary: bool) -> None:
    """Binary (or ASCII) PCD through pypcd4, in float32 whatever the input: PCL's convention, and Open3D reads
    binary SIZE 8 fields as zeros."""
    from pypcd4 import Encoding, PointCloud

    cloud = PointCloud.from_xyz_points(np.asarray(points, np.float32))
    cloud.save(f, encoding=Encoding.BINARY if binary else Encoding.ASCII)
