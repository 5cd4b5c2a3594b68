"""What the readers and writers of :mod:`dit_jax.io` share: the error and the warning they raise, the atomic
write, the coordinate columns, moving a record's coordinates and turning its normals, and faces fanned into
triangles."""

from __future__ import annotations

import contextlib
import os
import tempfile

import numpy as np

FORMATS = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".asc", ".pts", ".npy", ".las", ".laz")


#: The formats :func:`write` writes: all but LAS and LAZ, which are read (and moved: :func:`move_file`).
WRITE_FORMATS = tuple(f for f in FORMATS if f not in (".las", ".laz"))


#: Meshes, read as points sampled uniformly over their surface (:func:`read`, :func:`read_mesh`) and written
#: only as a mesh file moved (:func:`move_file`). A PLY or OBJ file without faces is a cloud.
MESH_FORMATS = (".obj", ".off", ".stl", ".ply")


#: How many surface points :func:`read` samples from a mesh: far more than registration samples from a cloud.
MESH_POINTS = 100_000


#: Every extension :func:`read` reads.
READ_FORMATS = FORMATS + tuple(f for f in MESH_FORMATS if f not in FORMATS)


#: The formats :func:`move_file` writes moved, every other property kept.
MOVE_FORMATS = (".ply", ".pcd", ".las", ".laz", ".obj", ".off", ".stl")


#: The formats read and written as text, one point per line.
TEXT_FORMATS = (".xyz", ".txt", ".csv", ".asc", ".pts")


class CloudFileError(ValueError):
    """A point-cloud file that cannot be read as (N, 3) finite coordinates; the message names the file."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class NonFiniteWarning(UserWarning):
    """Points with a NaN or Inf coordinate were left out of a file read with ``drop_nonfinite=True``."""

    def __init__(self, path: str | os.PathLike, dropped: int, rows: int):
        self.path, self.dropped, self.rows = os.fspath(path), dropped, rows
        super().__init__(f"{self.path}: left out {dropped:,} of {rows:,} points with NaN or Inf coordinates")


_XYZ = ("x", "y", "z")


_NORMALS = {".ply": ("nx", "ny", "nz"), ".pcd": ("normal_x", "normal_y", "normal_z")}


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def _columns(path: str, names: list[str]) -> list[int]:
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise CloudFileError(
            path, f"not three coordinates: no {'/'.join(missing)} field (fields: {' '.join(names) or 'none'})"
        )
    return [names.index(axis) for axis in "xyz"]


def _move_fields(
    table: np.ndarray, normals: tuple[str, str, str], rotation: np.ndarray, translation: np.ndarray
) -> None:
    """Moves x, y, z of a structured array of points in place, and turns its normals where it has them."""
    names = table.dtype.names
    groups = [(axes, axes is not _XYZ) for axes in (_XYZ, normals) if all(a in names for a in axes)]
    _move_columns([([table[a] for a in axes], is_normal) for axes, is_normal in groups], rotation, translation)


def _move_columns(groups: list[tuple[list[np.ndarray], bool]], rotation: np.ndarray, translation: np.ndarray) -> None:
    """Moves each group of three coordinate columns (views into a file's records, (N,) each) in place, or,
    where the group is a normal, turns it."""
    for views, is_normal in groups:
        values = np.stack([view.astype(np.float64) for view in views], axis=1) @ rotation.T
        for view, column in zip(views, (values if is_normal else values + translation).T):
            view[...] = column


def _fans(corners: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(F, 3) triangles splitting each polygon (``counts[i]`` consecutive entries of ``corners``) into a fan."""
    per_polygon = np.maximum(counts - 2, 0)  # a "face" of one or two corners has no area: nothing
    polygon = np.repeat(np.arange(len(counts)), per_polygon)
    first = (np.cumsum(counts) - counts)[polygon]
    step = np.arange(len(polygon)) - (np.cumsum(per_polygon) - per_polygon)[polygon] + 1
    return np.stack([corners[first], corners[first + step], corners[first + step + 1]], axis=1)


@contextlib.contextmanager
def _atomic_file(path: str):
    """A binary file object whose contents replace ``path`` only once the block ends without an error."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise CloudFileError(path, f"folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes files private; a written cloud is an ordinary file
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _text_format(points: np.ndarray) -> str:
    return "%.17g" if points.dtype == np.float64 else "%.9g"  # enough digits to read back the same value


def file_format(path: str | os.PathLike, kind: str = "format", formats: tuple[str, ...] = FORMATS) -> str:
    """The lower-case extension of ``path`` if it is one of ``formats``, else :class:`CloudFileError`."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in formats:
        raise CloudFileError(path, f"unknown {kind} {ext or '(no extension)'!r}; expected one of {', '.join(formats)}")
    return ext
