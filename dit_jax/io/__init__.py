"""Point-cloud files: read and write .ply, .pcd, text (.xyz, .txt, .csv, .asc, .pts) and .npy, read .las and
.laz and meshes (.obj, .off, .stl, .ply), refusing bad input with one-line errors.

Every reader returns an (N, 3) float64 array of coordinates and raises :class:`CloudFileError` (a ValueError
whose message names the file and the problem) for anything it cannot turn into one: a missing or unreadable
file, an unknown extension, a malformed header, values that are NaN or Inf (``drop_nonfinite=True`` leaves
those points out instead), or rows that are not three coordinates. The formats are parsed by well-kept
libraries where one reads them:

* PLY (plyfile): ascii and binary, the ``x``, ``y``, ``z`` properties of the ``vertex`` element; binary
  vertices are memory-mapped. A PLY file with faces (``vertex_indices``) is a mesh, sampled as the others are.
* PCD (pypcd4): ``ascii``, ``binary`` and ``binary_compressed``, fields ``x y z`` (others skipped).
* LAS and LAZ (laspy, with lazrs for LAZ): every version and point format, scaled and offset as the header says.
* STL, ASCII or binary: read here. Binary STL is one NumPy record per facet, faster than trimesh's reader,
  and trimesh refuses ASCII STL whose lines end in a lone carriage return (old Mac files), which this reads.
* OBJ and OFF: read here. trimesh drops the vertices of an OBJ without faces (a cloud) and refuses OFF
  files whose counts share the keyword's line (``OFF490 518 0``, as ModelNet's are written).
* Meshes of every format are sampled over their surface by trimesh (:func:`sample_surface`, seeded).
* Text (.xyz, .txt, .csv, .asc, .pts): one point per line, whitespace, comma or semicolon separated;
  columns after the third are ignored, ``#`` starts a comment, and a first line that is not three numbers is
  taken for a header and skipped (``x,y,z``, ``//X,Y,Z``, or the point count that opens a .pts file).
* NPY: an (N, 3) array of any real dtype, memory-mapped.

Where this module parses by hand, the reason is the format case named above or a speed measured against the
libraries (docs/benchmarks.md, "Reading files").

:func:`move_file` writes a PLY, PCD, LAS, LAZ or mesh file moved, every other field kept (``dit-register
--out`` with the source's own extension). Writers (:func:`write`) produce binary little-endian PLY (float or
double as the input), binary float32 PCD (what PCL and Open3D read), text with enough digits to round-trip
(17 for float64, 9 otherwise; .csv comma-separated under an ``x,y,z`` header, .pts after the point count) and
float32/64 NPY. They write to a temporary file in the destination's folder and rename it into place, so a
failure leaves nothing half-written.
"""

from __future__ import annotations

import os
import stat
import tokenize
import warnings

import numpy as np

from dit_jax.io.common import (
    FORMATS,
    MESH_FORMATS,
    MESH_POINTS,
    MOVE_FORMATS,
    READ_FORMATS,
    TEXT_FORMATS,
    WRITE_FORMATS,
    CloudFileError,
    NonFiniteWarning,
    _atomic_file,
    _columns,
    _first_line,
    _text_format,
    file_format,
)
from dit_jax.io.las import _moved_las, _read_las
from dit_jax.io.mesh import (
    _moved_binary_stl,
    _moved_text_mesh,
    _read_mesh_as_points,
    _stl_is_ascii,
    read_mesh,
    sample_surface,
)
from dit_jax.io.pcd import _moved_pcd, _read_pcd, _write_pcd
from dit_jax.io.ply import _ascii_ply_vertices, _moved_ply, _ply, _ply_triangles, _read_ply, _write_ply
from dit_jax.io.text import _read_npy, _read_text

__all__ = [
    "FORMATS",
    "MESH_FORMATS",
    "MESH_POINTS",
    "MOVE_FORMATS",
    "READ_FORMATS",
    "TEXT_FORMATS",
    "WRITE_FORMATS",
    "CloudFileError",
    "NonFiniteWarning",
    "file_format",
    "move_file",
    "read",
    "read_mesh",
    "sample_surface",
    "write",
]


def read(
    path: str | os.PathLike,
    *,
    max_points: int | None = None,
    seed: int = 0,
    return_count: bool = False,
    drop_nonfinite: bool = False,
    mesh_points: int = MESH_POINTS,
):
    """Reads the points of a .ply, .pcd, text (.xyz, .txt, .csv, .asc, .pts) or .npy file, or samples a mesh.

    Args:
      path: the file; its extension picks the format.
      max_points: files with more points than this give a uniform random subset of ``max_points`` of them
        (seeded by ``seed``, file order kept); binary PLY/PCD, LAS and NPY files never load the other rows.
      return_count: also return how many points the file holds.
      mesh_points: a mesh (.obj, .off, .stl, a PLY with faces; see :func:`read_mesh`) gives this many points
        (at most ``max_points``) sampled uniformly over its surface area, seeded by ``seed``: a CAD model's
        vertices crowd at its edges and leave its faces bare, unlike any scan. ``points_in_file`` is then the
        number sampled. An OBJ or PLY file without faces gives its vertices, as a cloud.
      drop_nonfinite: leave out points with a NaN or Inf coordinate instead of refusing the file, with a
        :class:`NonFiniteWarning` that says how many. Depth cameras and organized PCD files mark pixels
        without a return by NaN; elsewhere such values usually mean a broken export, hence the default. The
        file's every row is read to find them (``max_points`` then samples among the finite ones), and
        ``points_in_file`` counts only the finite ones.

    Returns:
      points: (N, 3) float64, all finite; with ``return_count`` the pair ``(points, points_in_file)``.

    Raises:
      CloudFileError: the file is missing, unreadable, of an unknown format, malformed, not three coordinates
        per point, or holds NaN or Inf values (unless ``drop_nonfinite``, and then only where no point is
        finite).
    """
    path = os.fspath(path)
    ext = file_format(path, formats=READ_FORMATS)
    _check_readable(path)
    if mesh_points < 1:
        raise ValueError(f"mesh_points must be positive, got {mesh_points}")
    reader = _reader(ext, mesh_points if max_points is None else min(mesh_points, max_points), seed)

    def select(count: int) -> np.ndarray | None:
        if max_points is None or count <= max_points:
            return None
        return np.sort(np.random.default_rng(seed).choice(count, max_points, replace=False))

    try:
        # Sampling before the finite points are known could keep too few of them, so dropping reads all rows.
        points, total = reader(path, (lambda count: None) if drop_nonfinite else select)
    except CloudFileError:
        raise
    except (OSError, ValueError, UnicodeDecodeError, EOFError, SyntaxError, tokenize.TokenError) as err:
        # SyntaxError and TokenError: an NPY header that does not parse as the dict numpy expects
        raise CloudFileError(path, f"unreadable {ext[1:].upper()} file ({_first_line(err)})") from None
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise CloudFileError(path, f"expected N x 3 coordinates, got an array of shape {points.shape}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any() and not drop_nonfinite:
        raise CloudFileError(
            path,
            f"{int(bad.sum())} of {len(points)} points have NaN or Inf coordinates "
            f"(first at row {int(np.argmax(bad))}); to leave them out, read with "
            f"drop_nonfinite=True (dit-register --drop-nonfinite)",
        )
    if drop_nonfinite:
        if len(points) and bad.all():
            raise CloudFileError(path, f"all {len(points)} points have NaN or Inf coordinates")
        if bad.any():
            warnings.warn(NonFiniteWarning(path, int(bad.sum()), len(points)), stacklevel=2)
            points = points[~bad]
        total = len(points)
        rows_kept = select(total)
        if rows_kept is not None:
            points = points[rows_kept]
    return (points, total) if return_count else points


def _check_readable(path: str) -> None:
    """:class:`CloudFileError` unless ``path`` is a regular file this process may read."""
    if not os.path.exists(path):
        raise CloudFileError(path, "no such file")
    if os.path.isdir(path):
        raise CloudFileError(path, "is a directory, not a point-cloud file")
    if not stat.S_ISREG(os.stat(path).st_mode):  # a pipe would block for ever, a device never end
        raise CloudFileError(path, "is not a regular file (a pipe, socket or device)")
    if not os.access(path, os.R_OK):
        raise CloudFileError(path, "permission denied")


def _reader(ext: str, n_samples: int, seed: int):
    """The function that reads a file of format ``ext``: ``(path, select) -> (points, points_in_file)``, where
    ``select(count)`` gives the rows to keep (None: all); a mesh gives ``n_samples`` points sampled with ``seed``."""
    if ext == ".ply":

        def reader(path_, select_):
            fast = _ascii_ply_vertices(path_)
            if fast is not None:
                rows, names = fast
                kept = select_(len(rows))
                return (rows if kept is None else rows[kept])[:, _columns(path_, names)], len(rows)
            ply = _ply(path_, mmap=True)
            if _ply_triangles(ply) is None:
                return _read_ply(path_, select_, ply)
            return _read_mesh_as_points(path_, select_, n_samples, seed)
    elif ext in MESH_FORMATS:

        def reader(path_, select_):
            return _read_mesh_as_points(path_, select_, n_samples, seed)
    else:
        reader = {".pcd": _read_pcd, ".npy": _read_npy, ".las": _read_las, ".laz": _read_las}.get(ext, _read_text)
    return reader


def write(path: str | os.PathLike, points: np.ndarray, *, binary: bool = True) -> None:
    """Writes (N, 3) points as .ply, .pcd (binary unless ``binary=False``), text or .npy, atomically."""
    path = os.fspath(path)
    ext = file_format(path, formats=WRITE_FORMATS)
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    with _atomic_file(path) as f:
        if ext == ".npy":
            np.save(f, points if points.dtype in (np.float32, np.float64) else points.astype(np.float64))
        elif ext == ".ply":
            _write_ply(f, points, binary)
        elif ext == ".pcd":
            _write_pcd(f, points, binary)
        elif ext == ".csv":
            np.savetxt(f, points, fmt=_text_format(points), delimiter=",", header="x,y,z", comments="")
        else:
            np.savetxt(
                f, points, fmt=_text_format(points), header=str(len(points)) if ext == ".pts" else "", comments=""
            )


def write_text(path: str | os.PathLike, text: str) -> None:
    """Writes ``text`` (UTF-8) to ``path`` atomically: a failed write leaves what was there."""
    with _atomic_file(os.fspath(path)) as f:
        f.write(text.encode("utf-8"))


def move_file(
    source: str | os.PathLike, destination: str | os.PathLike, rotation: np.ndarray, translation: np.ndarray
) -> None:
    """Writes the file ``source`` moved by ``x -> rotation @ x + translation`` to ``destination``, in the same
    format, atomically, with everything but the coordinates kept: points (every one) and vertices moved,
    normals turned, every other line or byte as it was. So a scan keeps its colours, intensities and
    classes, a mesh its faces, texture coordinates, groups and materials.

    * PLY (cloud or mesh): ``x, y, z`` moved, ``nx, ny, nz`` turned, other properties and elements kept.
    * PCD: ``x, y, z`` moved, ``normal_x, normal_y, normal_z`` turned, the ``VIEWPOINT`` (the sensor's pose)
      moved with the points, other fields kept; ``binary_compressed`` data is written as ``binary``.
    * LAS, LAZ: X, Y, Z moved and rounded to the file's scale (its stated precision), the header's bounds (and,
      where the moved points would overflow its integers, its offset) updated; every other attribute kept.
    * OBJ, OFF, STL: vertices moved, OBJ's ``vn`` and STL's facet normals turned, every other line kept (no
      mesh library writes a file back with its comments, groups and materials as they were).

    Args:
      source, destination: paths of the same format, one of :data:`MOVE_FORMATS`.
      rotation: (3, 3); translation: (3,) (a :class:`dit_jax.pipeline.result.Result`'s).

    Raises:
      CloudFileError: ``source`` is unreadable or malformed, ``destination`` has another format, or a PLY or
        PCD file stores its coordinates as integers (moving them would round them).
    """
    source, destination = os.fspath(source), os.fspath(destination)
    ext = file_format(source, kind="format to move", formats=MOVE_FORMATS)
    if os.path.splitext(destination)[1].lower() != ext:
        raise CloudFileError(destination, f"a moved {ext} file is written as {ext} (the source's format)")
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    if not os.path.isfile(source):
        raise CloudFileError(source, "no such file" if not os.path.exists(source) else "is not a file")
    content = None  # the moved file, made whole before anything is written
    try:
        if ext == ".ply":
            content = _moved_ply(source, rotation, translation)
        elif ext == ".pcd":
            content = _moved_pcd(source, rotation, translation)
        elif ext in (".las", ".laz"):
            content = _moved_las(source, rotation, translation)
        elif ext == ".stl" and not _stl_is_ascii(source):
            content = _moved_binary_stl(source, rotation, translation)
        else:
            read_mesh(source)
            content = _moved_text_mesh(source, ext, rotation, translation)
    except CloudFileError:
        raise
    except (OSError, ValueError, IndexError, UnicodeDecodeError) as err:
        raise CloudFileError(source, f"unreadable {ext[1:].upper()} file ({_first_line(err)})") from None
    with _atomic_file(destination) as out:
        out.write(content)
