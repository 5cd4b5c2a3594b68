"""Point-cloud files: read and write .ply, .pcd, text (.xyz, .txt, .csv, .asc, .pts) and .npy, read .las and
meshes (.obj, .off, .stl, .ply), refusing bad input with one-line errors.

Every reader returns an (N, 3) float64 array of coordinates and raises :class:`CloudFileError` (a ValueError
whose message names the file and the problem) for anything it cannot turn into one: a missing or unreadable
file, an unknown extension, a malformed header, values that are NaN or Inf (``drop_nonfinite=True`` leaves
those points out instead), or rows that are not three coordinates. Formats:

* PLY: ``ascii``, ``binary_little_endian`` and ``binary_big_endian``; the ``x``, ``y``, ``z`` properties of the
  ``vertex`` element (other properties and elements are skipped). Binary files are memory-mapped. A PLY file
  with faces (a ``face`` element with ``vertex_indices``) is a mesh, sampled as the others are.
* PCD: ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, unpacked in pure Python; timings in
  docs/BENCHMARKS.md "Reading files") with fields ``x y z`` (any others skipped).
* Text (.xyz, .txt, .csv, .asc, .pts): one point per line, whitespace, comma or semicolon separated;
  columns after the third (normals, colours, intensity) are ignored, ``#`` starts a comment, and a first
  line that is not three numbers is taken for a header and skipped (column names such as ``x,y,z`` or
  ``//X,Y,Z``, or the point count that opens a .pts file).
* NPY: an (N, 3) array of any real dtype, memory-mapped.
* LAS (read, and written only as a file moved): ASPRS LAS 1.0-1.4, every point data format, memory-mapped;
  X, Y, Z scaled and offset as the header says. Compressed LAZ is refused with the hint to decompress it.
* Meshes (:data:`MESH_FORMATS`): .obj, .off, .stl and PLY with faces, sampled uniformly over their surface.

:func:`move_file` writes a PLY, PCD, LAS or mesh file moved, every other field kept (``dit-register --out``
with the source's own extension). Writers (:func:`write`) produce binary little-endian PLY (float or double
as the input), binary float32 PCD (what PCL and Open3D read), text with enough digits to round-trip (17 for
float64, 9 otherwise; .csv comma-separated under an ``x,y,z`` header, .pts after the point count) and
float32/64 NPY. They write to a temporary file in the destination's folder and rename it into place, so a
failure leaves nothing half-written.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import tempfile
import warnings
from typing import NamedTuple

import numpy as np

FORMATS = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".asc", ".pts", ".npy", ".las")
#: The formats :func:`write` writes: all but LAS, which is read (and moved: :func:`move_file`).
WRITE_FORMATS = tuple(f for f in FORMATS if f != ".las")
#: Meshes, read as points sampled uniformly over their surface (:func:`read`, :func:`read_mesh`) and written
#: only as a mesh file moved (:func:`move_file`). A PLY or OBJ file without faces is a cloud.
MESH_FORMATS = (".obj", ".off", ".stl", ".ply")
#: How many surface points :func:`read` samples from a mesh: far more than registration samples from a cloud.
MESH_POINTS = 100_000
_READ_FORMATS = FORMATS + tuple(f for f in MESH_FORMATS if f not in FORMATS)
#: The formats :func:`move_file` writes moved, every other property kept.
MOVE_FORMATS = (".ply", ".pcd", ".las", ".obj", ".off", ".stl")
#: The formats read and written as text, one point per line.
TEXT_FORMATS = (".xyz", ".txt", ".csv", ".asc", ".pts")

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


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


def file_format(path: str | os.PathLike, kind: str = "format", formats: tuple[str, ...] = FORMATS) -> str:
    """The lower-case extension of ``path`` if it is one of ``formats``, else :class:`CloudFileError`."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in formats:
        raise CloudFileError(path, f"unknown {kind} {ext or '(no extension)'!r}; expected one of "
                                   f"{', '.join(formats)}")
    return ext


def read(path: str | os.PathLike, *, max_points: int | None = None, seed: int = 0,
         return_count: bool = False, drop_nonfinite: bool = False, mesh_points: int = MESH_POINTS):
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
    ext = file_format(path, formats=_READ_FORMATS)
    if not os.path.exists(path):
        raise CloudFileError(path, "no such file")
    if os.path.isdir(path):
        raise CloudFileError(path, "is a directory, not a point-cloud file")
    if not os.access(path, os.R_OK):
        raise CloudFileError(path, "permission denied")
    if mesh_points < 1:
        raise ValueError(f"mesh_points must be positive, got {mesh_points}")
    n_samples = mesh_points if max_points is None else min(mesh_points, max_points)
    if ext == ".ply":
        def reader(path_, select_):
            layout = _ply_layout(path_)
            if layout.faces() is None:
                return _read_ply(path_, select_, layout)
            return _read_mesh_as_points(path_, select_, n_samples, seed)
    elif ext in MESH_FORMATS:
        def reader(path_, select_):
            return _read_mesh_as_points(path_, select_, n_samples, seed)
    else:
        reader = {".pcd": _read_pcd, ".npy": _read_npy, ".las": _read_las}.get(ext, _read_text)
    def select(count: int) -> np.ndarray | None:
        if max_points is None or count <= max_points:
            return None
        return np.sort(np.random.default_rng(seed).choice(count, max_points, replace=False))

    try:
        # Sampling before the finite points are known could keep too few of them, so dropping reads all rows.
        points, total = reader(path, (lambda count: None) if drop_nonfinite else select)
    except CloudFileError:
        raise
    except (OSError, ValueError, UnicodeDecodeError, EOFError) as err:
        raise CloudFileError(path, f"unreadable {ext[1:].upper()} file ({_first_line(err)})") from None
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise CloudFileError(path, f"expected N x 3 coordinates, got an array of shape {points.shape}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any() and not drop_nonfinite:
        raise CloudFileError(path, f"{int(bad.sum())} of {len(points)} points have NaN or Inf coordinates "
                                   f"(first at row {int(np.argmax(bad))}); to leave them out, read with "
                                   f"drop_nonfinite=True (dit-register --drop-nonfinite)")
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
            np.savetxt(f, points, fmt=_text_format(points), header=str(len(points)) if ext == ".pts" else "",
                       comments="")


def move_file(source: str | os.PathLike, destination: str | os.PathLike, rotation: np.ndarray,
              translation: np.ndarray) -> None:
    """Writes the file ``source`` moved by ``x -> rotation @ x + translation`` to ``destination``, in the same
    format, atomically, with everything but the coordinates kept: points (every one) and vertices moved,
    normals turned, every other line or byte as it was. So a scan keeps its colours, intensities and
    classes, a mesh its faces, texture coordinates, groups and materials.

    * PLY (cloud or mesh): ``x, y, z`` moved, ``nx, ny, nz`` turned, other properties and elements kept.
    * PCD: ``x, y, z`` moved, ``normal_x, normal_y, normal_z`` turned, the ``VIEWPOINT`` (the sensor's pose)
      moved with the points, other fields kept; ``binary_compressed`` data is written as ``binary``.
    * LAS: X, Y, Z moved and rounded to the file's scale (its stated precision), the header's bounds (and,
      where the moved points would overflow its integers, its offset) updated; every other byte kept.
    * OBJ, OFF, STL: vertices moved, OBJ's ``vn`` and STL's facet normals turned.

    Args:
      source, destination: paths of the same format, one of :data:`MOVE_FORMATS`.
      rotation: (3, 3); translation: (3,) (a :class:`dit_jax.registration.Result`'s).

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
    content = None  # the moved file (a LAS file is streamed instead), made before anything is written
    try:
        if ext == ".ply":
            content = _moved_ply(source, rotation, translation)
        elif ext == ".pcd":
            content = _moved_pcd(source, rotation, translation)
        elif ext == ".las":
            _las_records(source)  # refuses what it cannot read (header and size; the records are read once, below)
        elif ext == ".stl" and not _stl_is_ascii(source):
            read_mesh(source)
            with open(source, "rb") as f:
                head, records = f.read(84), np.frombuffer(f.read(), _STL_RECORD).copy()
            records["corners"] = records["corners"].astype(np.float64) @ rotation.T + translation
            records["normal"] = records["normal"].astype(np.float64) @ rotation.T
            content = head + records.tobytes()
        else:
            read_mesh(source)
            content = _moved_text_mesh(source, ext, rotation, translation)
    except CloudFileError:
        raise
    except (OSError, ValueError, IndexError, UnicodeDecodeError) as err:
        raise CloudFileError(source, f"unreadable {ext[1:].upper()} file ({_first_line(err)})") from None
    with _atomic_file(destination) as out:
        if content is None:
            _write_moved_las(out, source, rotation, translation)
        else:
            out.write(content)


def _moved_text_mesh(path: str, ext: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of an OBJ, OFF or ASCII STL file with its vertices moved and its normals turned: each such line
    is written again as its words joined by single spaces, a comment at its end and its line end kept."""
    with open(path, "r", encoding="utf-8", errors="surrogateescape", newline="") as f:  # "\r\n" stays
        lines = f.readlines()
    numbers = _mesh_coordinate_lines(path, ext, lines)
    rows = [lines[n].rstrip("\r\n") for n in numbers]
    tails = [lines[n][len(row):] for n, row in zip(numbers, rows)]  # the line ends
    if any("#" in row for row in rows):
        parts = [row.partition("#") for row in rows]
        rows = [code for code, _, _ in parts]
        tails = [f" {hash_}{comment}{end}" if hash_ else end for (_, hash_, comment), end in zip(parts, tails)]
    words, offsets = _row_words(rows)
    # per line: where its three numbers start (after "v", "vn", "vertex", "facet normal"), and whether they are
    # a normal, which turns but does not move
    kind = {"v": (1, False), "vn": (1, True), "vertex": (1, False), "facet": (2, True)}
    first = map(str.lower, _picked(words, offsets[:-1])) if ext != ".off" else itertools.repeat("", len(rows))
    starts, normal = np.array([kind.get(word, (0, False)) for word in first], np.int64).reshape(-1, 2).T
    if (np.diff(offsets) < starts + 3).any():
        raise CloudFileError(path, "a vertex or normal line has fewer than three coordinates")
    index = (offsets[:-1] + starts)[:, None] + np.arange(3)
    xyz = _floats(_picked(words, index)).reshape(-1, 3) @ rotation.T
    xyz += np.where(normal[:, None].astype(bool), 0.0, translation)
    # All rows rebuilt at once: words and separators interleaved, the moved numbers put in place, one join.
    pieces = np.full(2 * len(words), " ", object)
    pieces[0::2] = words
    pieces[2 * offsets[1:] - 1] = "\n"
    pieces[2 * index.ravel()] = list(map(repr, xyz.ravel().tolist()))
    moved = "".join(pieces.tolist()).split("\n")
    for n, row, tail in zip(numbers, moved, tails):
        lines[n] = row + tail
    return "".join(lines).encode("utf-8", errors="surrogateescape")


def _moved_ply(path: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of PLY file ``path`` with its vertices' x, y, z moved and nx, ny, nz turned (if it has them)."""
    layout = _ply_layout(path)
    index = layout.index("vertex")
    props = dict(layout.elements[index].props)
    groups = [(axes, axes is not _XYZ) for axes in (_XYZ, _NORMALS[".ply"]) if all(a in props for a in axes)]
    if any(np.dtype(props[a]).kind != "f" for a in _XYZ):
        raise CloudFileError(path, "PLY coordinates stored as integers would be rounded when moved; "
                                   "write the moved points to another file instead")
    with open(path, "rb") as f:
        data = f.read()
    if layout.fmt != "ascii":
        start = _ply_binary_start(path, layout, index, np.frombuffer(data, np.uint8))
        record, count = _ply_vertex_record(layout), layout.elements[index].count
        table = np.frombuffer(data, record, count, start).copy()
        _move_columns([([table[a] for a in axes], is_normal) for axes, is_normal in groups], rotation, translation)
        return data[:start] + table.tobytes() + data[start + count * record.itemsize:]
    skip, count = _ply_text_span(layout, index)
    lines = data[layout.offset:].split(b"\n")
    if len(lines) < skip + count:
        raise CloudFileError(path, f"PLY file ends before its {count} vertices")
    names = [n for n, _ in layout.elements[index].props]
    columns = [([names.index(a) for a in axes], is_normal, np.dtype(props[axes[0]]).itemsize == 4)
               for axes, is_normal in groups]
    block = _moved_text_rows(path, lines[skip:skip + count], len(names), columns, rotation, translation)
    return data[:layout.offset] + b"\n".join(lines[:skip] + block + lines[skip + count:])


def _move_columns(groups: list[tuple[list[np.ndarray], bool]], rotation: np.ndarray,
                  translation: np.ndarray) -> None:
    """Moves each group of three coordinate columns (views into a file's records, (N,) each) in place, or,
    where the group is a normal, turns it."""
    for views, is_normal in groups:
        values = np.stack([view.astype(np.float64) for view in views], axis=1) @ rotation.T
        for view, column in zip(views, (values if is_normal else values + translation).T):
            view[...] = column


def _moved_text_rows(path: str, rows: list[bytes], width: int, columns: list[tuple[list[int], bool, bool]],
                     rotation: np.ndarray, translation: np.ndarray) -> list[bytes]:
    """Text rows of ``width`` whitespace-separated values each (an ASCII PLY or PCD file's points, line ends
    not included) with three columns moved, or turned, at a time.

    Args:
      columns: per group (three column indices, whether they are a normal, which turns but does not move,
        whether they are single precision, written with 9 digits instead of the 17 of a double's repr).

    Every row is rebuilt from its values joined by single spaces (``\\r`` line ends kept).
    """
    tokens = b" ".join(rows).split()
    if len(tokens) != len(rows) * width:
        raise CloudFileError(path, f"expected {width} values on each of {len(rows)} point rows, "
                                   f"found {len(tokens)} values")
    for cols, is_normal, single in columns:
        values = np.stack([np.array(tokens[c::width]).astype(np.float64) for c in cols], axis=1) @ rotation.T
        values = values if is_normal else values + translation
        text = list(map(b"%.9g".__mod__ if single else b"%r".__mod__, values.reshape(-1).tolist()))
        for k, c in enumerate(cols):
            tokens[c::width] = text[k::3]
    end = b"\r" if rows and rows[0].endswith(b"\r") else b""
    parts = [b" "] * (2 * len(tokens))
    parts[0::2] = tokens
    parts[2 * width - 1::2 * width] = [end + b"\n"] * len(rows)
    return b"".join(parts)[:-1].split(b"\n") if rows else []


_XYZ = ("x", "y", "z")
_NORMALS = {".ply": ("nx", "ny", "nz"), ".pcd": ("normal_x", "normal_y", "normal_z")}


def _moved_pcd(path: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of PCD file ``path`` with x, y, z moved, normal_x, normal_y, normal_z turned and the
    VIEWPOINT moved; ``binary_compressed`` data comes back as ``binary`` (PCL and Open3D read both)."""
    layout = _pcd_layout(path)
    header, names = list(layout.header), layout.names
    _columns(path, names)
    if any(layout.types[names.index(a)] != "F" for a in _XYZ):
        raise CloudFileError(path, "PCD coordinates stored as integers would be rounded when moved; "
                                   "write the moved points to another file instead")
    if any(layout.counts[names.index(a)] != 1 for a in _XYZ):
        raise CloudFileError(path, "PCD x/y/z fields must have COUNT 1")
    groups = [(axes, axes is not _XYZ) for axes in (_XYZ, _NORMALS[".pcd"]) if all(a in names for a in axes)]

    if "VIEWPOINT" in layout.lines:  # the sensor's pose in the cloud's frame: tx ty tz qw qx qy qz
        number = layout.lines["VIEWPOINT"]
        view = np.asarray(header[number].split()[1:8], np.float64)
        pose = (*(rotation @ view[:3] + translation), *_quaternion_product(_rotation_quaternion(rotation), view[3:]))
        header[number] = "VIEWPOINT " + " ".join(f"{v:.17g}" for v in pose) + "\n"
    with open(path, "rb") as f:
        f.seek(layout.offset)
        data = f.read()
    if layout.data == "ascii":
        starts = np.cumsum([0] + layout.counts)[:-1]
        columns = [([int(starts[names.index(a)]) for a in axes], is_normal, layout.sizes[names.index(axes[0])] == 4)
                   for axes, is_normal in groups]
        rows = [row for row in data.split(b"\n") if row.strip()]
        if len(rows) != layout.count:
            raise CloudFileError(path, f"PCD header says {layout.count} points, the data has {len(rows)}")
        body = b"\n".join(_moved_text_rows(path, rows, sum(layout.counts), columns, rotation, translation) + [b""])
    else:
        if layout.data == "binary":
            record = _pcd_record(path, layout)
            table, rest = np.frombuffer(data, record, layout.count).copy(), data[layout.count * record.itemsize:]
        else:
            table, rest = _pcd_compressed_table(path, layout), b""
            header[layout.lines["DATA"]] = "DATA binary\n"
        fields = [([table[f"{a}_{names.index(a)}"][:, 0] for a in axes], is_normal) for axes, is_normal in groups]
        _move_columns(fields, rotation, translation)
        body = table.tobytes() + rest
    return "".join(header).encode("ascii", errors="surrogateescape") + body


def _rotation_quaternion(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of a rotation matrix (3, 3), w >= 0."""
    m = np.asarray(rotation, np.float64)
    # the largest of 4w^2, 4x^2, 4y^2, 4z^2 gives the best-conditioned square root
    squares = np.array([1 + np.trace(m), 1 + m[0, 0] - m[1, 1] - m[2, 2], 1 - m[0, 0] + m[1, 1] - m[2, 2],
                        1 - m[0, 0] - m[1, 1] + m[2, 2]])
    k = int(np.argmax(squares))
    r = np.sqrt(max(squares[k], 0.0)) * 2  # 4 * |component k|
    off = {0: (m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]),
           1: (m[2, 1] - m[1, 2], m[0, 1] + m[1, 0], m[0, 2] + m[2, 0]),
           2: (m[0, 2] - m[2, 0], m[0, 1] + m[1, 0], m[1, 2] + m[2, 1]),
           3: (m[1, 0] - m[0, 1], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1])}[k]
    q = np.empty(4)
    q[k] = r / 4
    q[[i for i in range(4) if i != k]] = np.asarray(off) / r
    return q if q[0] >= 0 else -q


def _quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a * b for quaternions (w, x, y, z): the rotation b, then a."""
    (aw, ax, ay, az), (bw, bx, by, bz) = a, b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def _write_moved_las(out, path: str, rotation: np.ndarray, translation: np.ndarray) -> None:
    """Writes LAS file ``path`` to ``out`` with its points moved, a million records at a time."""
    source, records, (data_offset, record_length, count, scale, offset) = _las_records(path)
    chunks = range(0, count, 1_000_000)

    def moved(chunk: np.ndarray, origin: np.ndarray) -> np.ndarray:  # chunk: (n, record_length) bytes
        return (np.ascontiguousarray(chunk[:, :12]).view("<i4") * scale + origin) @ rotation.T + translation

    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for start in chunks:
        points = moved(records[start:start + 1_000_000], offset)
        low, high = np.minimum(low, points.min(axis=0)), np.maximum(high, points.max(axis=0))
    new_offset = offset
    limit = 2 ** 31 - 2 ** 20  # int32, with room for rounding
    if count and ((np.abs((low - offset) / scale) > limit) | (np.abs((high - offset) / scale) > limit)).any():
        new_offset = np.round((low + high) / 2 / scale) * scale  # re-centre the integers on the moved points
    out.write(source[:data_offset].tobytes())
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for start in chunks:
        chunk = np.array(records[start:start + 1_000_000])  # every byte of each record, X, Y, Z replaced
        xyz = np.round((moved(chunk, offset) - new_offset) / scale).astype("<i4")
        chunk[:, :12] = xyz.view(np.uint8).reshape(len(chunk), 12)
        out.write(chunk.tobytes())
        low, high = np.minimum(low, xyz.min(axis=0)), np.maximum(high, xyz.max(axis=0))
    out.write(source[data_offset + count * record_length:].tobytes())  # EVLRs, waveforms
    if count:  # the header's offset, then its bounds (max x, min x, max y, ...) as the points now lie
        bounds = np.stack([high, low], axis=1) * scale[:, None] + new_offset[:, None]
        out.seek(155)
        out.write(new_offset.astype("<f8").tobytes() + bounds.reshape(-1).astype("<f8").tobytes())


def _mesh_coordinate_lines(path: str, ext: str, lines: list[str]) -> list[int]:
    """Indices of the lines of a text mesh that hold a vertex or a normal."""
    if ext == ".obj":
        return [i for i, line in enumerate(lines) if line.startswith(("v ", "vn ", "v\t", "vn\t"))]
    if ext == ".stl":
        text = "\n" + "".join(lines)  # so the first line has a line end before it too
        starts = [m.start() for m in _STL_COORDINATE_LINE.finditer(text)]  # = where the lines start in the file
        line_starts = np.cumsum([0] + [len(line) for line in lines])
        return (np.searchsorted(line_starts, starts, side="right") - 1).tolist()
    return _off_layout(path, lines)[0]


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


# ----------------------------------------------------------------------------------------------- readers


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def _read_header(f, path: str, end: bytes, limit: int = 1000) -> list[str]:
    lines = []
    for _ in range(limit):
        raw = f.readline()
        if not raw:
            raise CloudFileError(path, f"header ended without {end.decode()!r}")
        line = raw.decode("ascii", errors="replace").strip()
        lines.append(line)
        if raw.strip().startswith(end):
            return lines
    raise CloudFileError(path, f"no {end.decode()!r} in the first {limit} header lines")


def _columns(path: str, names: list[str]) -> list[int]:
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise CloudFileError(path, f"not three coordinates: no {'/'.join(missing)} field "
                                   f"(fields: {' '.join(names) or 'none'})")
    return [names.index(axis) for axis in "xyz"]


def _binary_records(path: str, dtype: np.dtype, offset: int, count: int, select, too_short: str) -> np.ndarray:
    """The ``count`` records at ``offset``, memory-mapped, then the rows ``select`` keeps (all if None)."""
    if os.path.getsize(path) < offset + count * dtype.itemsize:
        raise CloudFileError(path, too_short.format(count))
    if count == 0:
        return np.zeros(0, dtype)
    table = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(count,))
    rows_kept = select(count)
    return table if rows_kept is None else table[rows_kept]


class _PlyElement(NamedTuple):
    name: str
    count: int
    #: (name, dtype) per property: a NumPy type code for a scalar, (count type, item type) for a list
    props: list[tuple[str, str | tuple[str, str]]]

    @property
    def has_lists(self) -> bool:
        return any(isinstance(t, tuple) for _, t in self.props)


class _PlyLayout(NamedTuple):
    fmt: str  # ascii, binary_little_endian or binary_big_endian
    elements: list[_PlyElement]
    offset: int  # where the data starts

    @property
    def order(self) -> str:
        return "<" if self.fmt == "binary_little_endian" else ">"

    def index(self, name: str) -> int | None:
        names = [e.name for e in self.elements]
        return names.index(name) if name in names else None

    def faces(self) -> tuple[int, str] | None:
        """The face element's index and the name of its list of vertex indices, if it has faces at all."""
        index = self.index("face")
        if index is None or not self.elements[index].count:
            return None
        lists = [n for n, t in self.elements[index].props if isinstance(t, tuple)]
        name = next((n for n in ("vertex_indices", "vertex_index") if n in lists), None)
        return None if name is None else (index, name)


def _ply_layout(path: str) -> _PlyLayout:
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise CloudFileError(path, "not a PLY file (first line is not 'ply')")
        header = _read_header(f, path, b"end_header")
        offset = f.tell()
    fmt, elements = None, []
    for line in header:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_PlyElement(words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list" and len(words) == 5 and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES:
                elements[-1].props.append((words[4], (_PLY_TYPES[words[2]], _PLY_TYPES[words[3]])))
            elif words[1] in _PLY_TYPES and len(words) == 3:
                elements[-1].props.append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise CloudFileError(path, f"unsupported PLY property line {line!r}")
        else:
            raise CloudFileError(path, f"malformed PLY header line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise CloudFileError(path, f"unknown PLY format {fmt!r}")
    layout = _PlyLayout(fmt, elements, offset)
    index = layout.index("vertex")
    if index is None:
        raise CloudFileError(path, "PLY file has no vertex element")
    _columns(path, [n for n, _ in elements[index].props])
    if elements[index].has_lists:
        raise CloudFileError(path, "PLY vertex element has list properties; only scalar properties are read")
    return layout


def _ply_vertex_record(layout: _PlyLayout) -> np.dtype:
    props = layout.elements[layout.index("vertex")].props
    return np.dtype([(n if n else f"_{i}", layout.order + t) for i, (n, t) in enumerate(props)])


def _ply_text_span(layout: _PlyLayout, index: int) -> tuple[int, int]:
    """Where element ``index`` of an ASCII PLY file lies: (lines after the header before its first item, its
    item count). Every item takes one line, so the elements before it take one line per item."""
    return sum(e.count for e in layout.elements[:index]), layout.elements[index].count


def _ply_text_rows(path: str, layout: _PlyLayout, index: int) -> list[str]:
    """The text lines of element ``index`` of an ASCII PLY file (one line per item)."""
    skip, count = _ply_text_span(layout, index)
    with open(path, "rb") as f:
        f.seek(layout.offset)
        for _ in range(skip):
            f.readline()
        rows = [f.readline().decode("ascii", errors="replace") for _ in range(count)]
    if count and not rows[-1]:
        raise CloudFileError(path, f"PLY file ends before its {count} {layout.elements[index].name} items")
    return rows


def _ply_binary_start(path: str, layout: _PlyLayout, index: int, data: np.ndarray) -> int:
    """The byte at which element ``index`` of a binary PLY file starts: elements before it are walked."""
    start = layout.offset
    for element in layout.elements[:index]:
        start = _ply_binary_lists(path, layout, element, start, data)[0]
    return start


def _ply_binary_lists(path: str, layout: _PlyLayout, element: _PlyElement, start: int,
                      data: np.ndarray) -> tuple[int, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Where ``element`` (starting at byte ``start`` of ``data``, the file's bytes) ends, and each list property
    as (counts (count,), items (sum of counts,)).

    Lists usually all have one length (a triangle mesh): the rows are then one fixed record, read at once.
    Otherwise (triangles and quads mixed) they are walked row by row.
    """
    order, count = layout.order, element.count
    scalar = [np.dtype(order + t).itemsize if not isinstance(t, tuple) else None for _, t in element.props]
    lists = [(n, t) for n, t in element.props if isinstance(t, tuple)]
    if not lists:
        end = start + count * sum(scalar)
        if end > len(data):
            raise CloudFileError(path, f"PLY file ends before its {count} {element.name} items")
        return end, {}
    if count == 0:
        return start, {n: (np.zeros(0, np.int64), np.zeros(0, np.int64)) for n, _ in lists}
    buffer = memoryview(data)
    first, pos = [], start
    for (name, t), size in zip(element.props, scalar):  # the first row's list lengths
        if size is None:
            if pos + np.dtype(t[0]).itemsize > len(data):
                raise CloudFileError(path, f"PLY file ends before its {count} {element.name} items")
            first.append(int(np.frombuffer(buffer, order + t[0], 1, pos)[0]))
            pos += np.dtype(t[0]).itemsize + first[-1] * np.dtype(t[1]).itemsize
        else:
            pos += size
    fields, lengths = [], iter(first)
    for i, (name, t) in enumerate(element.props):
        if isinstance(t, tuple):
            fields += [(f"{name}#n", order + t[0]), (f"{name}#items", order + t[1], (next(lengths),))]
        else:
            fields.append((f"_{i}", order + t))
    record = np.dtype(fields)
    end = start + count * record.itemsize
    if count and end <= len(data):
        table = np.frombuffer(buffer, record, count, start)
        if all((table[f"{n}#n"] == k).all() for (n, _), k in zip(lists, first)):
            return end, {n: (np.full(count, k, np.int64), table[f"{n}#items"].reshape(-1).astype(np.int64))
                         for (n, _), k in zip(lists, first)}
    # lists of several lengths: walk the rows
    found = {n: ([], []) for n, _ in lists}
    pos = start
    try:
        for _ in range(count):
            for (name, t), size in zip(element.props, scalar):
                if size is not None:
                    pos += size
                    continue
                n = int(np.frombuffer(buffer, order + t[0], 1, pos)[0])
                pos += np.dtype(t[0]).itemsize
                found[name][0].append(n)
                found[name][1].append(np.frombuffer(buffer, order + t[1], n, pos))
                pos += n * np.dtype(t[1]).itemsize
    except ValueError:  # frombuffer past the end
        raise CloudFileError(path, f"PLY file ends before its {count} {element.name} items") from None
    if pos > len(data):
        raise CloudFileError(path, f"PLY file ends before its {count} {element.name} items")
    return pos, {n: (np.asarray(c, np.int64), np.concatenate(items).astype(np.int64) if items else
                     np.zeros(0, np.int64)) for n, (c, items) in found.items()}


def _read_ply(path: str, select, layout: _PlyLayout | None = None) -> tuple[np.ndarray, int]:
    """The vertices of a PLY file (``select`` picks the rows kept) and how many it holds."""
    layout = layout or _ply_layout(path)
    index = layout.index("vertex")
    count, props = layout.elements[index].count, layout.elements[index].props
    cols = _columns(path, [n for n, _ in props])
    if layout.fmt == "ascii":
        rows = _ply_text_rows(path, layout, index)
        table = np.loadtxt(rows, dtype=np.float64, ndmin=2, usecols=range(len(props)))
        table = table[:, cols] if count else np.zeros((0, 3))
        rows_kept = select(count)
        return (table if rows_kept is None else table[rows_kept]), count
    start = _ply_binary_start(path, layout, index, np.memmap(path, np.uint8, mode="r"))
    table = _binary_records(path, _ply_vertex_record(layout), start, count, select,
                            "PLY file ends before its {} vertices")
    return np.stack([table[axis].astype(np.float64) for axis in "xyz"], axis=1), count


def _read_ply_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    layout = _ply_layout(path)
    vertices, _ = _read_ply(path, lambda count: None, layout)
    faces = layout.faces()
    if faces is None:
        return vertices, np.zeros((0, 3), np.int64)
    index, name = faces
    element = layout.elements[index]
    if layout.fmt == "ascii":
        counts, corners = [], []
        for number, row in enumerate(_ply_text_rows(path, layout, index)):
            words, at = row.split(), 0
            for prop, t in element.props:
                if not isinstance(t, tuple):
                    at += 1
                    continue
                n = int(words[at])
                if prop == name:
                    counts.append(n)
                    corners.extend(words[at + 1:at + 1 + n])
                at += 1 + n
            if at > len(words):
                raise CloudFileError(path, f"PLY face {number} lists fewer values than its properties need")
        counts, corners = np.asarray(counts, np.int64), np.asarray(corners, np.int64)
    else:
        data = np.memmap(path, np.uint8, mode="r")
        start = _ply_binary_start(path, layout, index, data)
        counts, corners = _ply_binary_lists(path, layout, element, start, data)[1][name]
    return vertices, _fans(corners, counts)


def _las_layout(path: str) -> tuple[int, int, int, np.ndarray, np.ndarray]:
    """A LAS file's point data offset, record length, point count, scale (3,) and offset (3,)."""
    with open(path, "rb") as f:
        header = f.read(375)
    if len(header) < 227 or header[:4] != b"LASF":
        raise CloudFileError(path, "not a LAS file (no LASF signature)")
    version = (header[24], header[25])
    data_offset = int(np.frombuffer(header, "<u4", 1, 96)[0])
    point_format, record_length = header[104], int(np.frombuffer(header, "<u2", 1, 105)[0])
    if point_format & 0xC0:  # LAZ marks compressed records in the top bits of the format
        raise CloudFileError(path, "compressed LAS (LAZ) is not supported; decompress it first (laszip)")
    count = int(np.frombuffer(header, "<u4", 1, 107)[0])
    if version >= (1, 4) and len(header) >= 255:  # 1.4 keeps a 64-bit count; the legacy one may be 0
        count = max(count, int(np.frombuffer(header, "<u8", 1, 247)[0]))
    if record_length < 12:
        raise CloudFileError(path, f"LAS point records of {record_length} bytes cannot hold X, Y, Z")
    scale, offset = np.frombuffer(header, "<f8", 3, 131), np.frombuffer(header, "<f8", 3, 155)
    return data_offset, record_length, count, scale, offset


def _las_records(path: str) -> tuple[np.ndarray, np.ndarray, tuple]:
    """A LAS file memory-mapped, its point records as (count, record_length) bytes and :func:`_las_layout`;
    :class:`CloudFileError` where the header is not one or the file ends before its records."""
    layout = data_offset, record_length, count, _, _ = _las_layout(path)
    source = np.memmap(path, np.uint8, mode="r")
    if len(source) < data_offset + count * record_length:
        raise CloudFileError(path, f"LAS file ends before its {count} points")
    return source, source[data_offset:data_offset + count * record_length].reshape(count, record_length), layout


def _read_las(path: str, select) -> tuple[np.ndarray, int]:
    """LAS 1.0-1.4 (ASPRS), any point data format: each record opens with X, Y, Z as int32, in units of the
    header's scale, from its offset. LAZ (compressed) is refused."""
    data_offset, record_length, count, scale, offset = _las_layout(path)
    record = np.dtype({"names": ["xyz"], "formats": [("<i4", 3)], "offsets": [0], "itemsize": record_length})
    table = _binary_records(path, record, data_offset, count, select, "LAS file ends before its {} points")
    return table["xyz"] * scale + offset, count


class _PcdLayout(NamedTuple):
    header: list[str]  # the header's lines, line ends kept
    lines: dict[str, int]  # the line number of each keyword (FIELDS, VIEWPOINT, DATA, ...)
    names: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    count: int  # points
    data: str  # ascii, binary or binary_compressed
    offset: int  # where the data starts


def _pcd_layout(path: str) -> _PcdLayout:
    with open(path, "rb") as f:
        _read_header(f, path, b"DATA")
        offset = f.tell()
        f.seek(0)
        header = f.read(offset).decode("ascii", errors="surrogateescape").splitlines(keepends=True)
    fields: dict[str, list[str]] = {}
    lines = {}
    for number, line in enumerate(header):
        words = line.split()
        if words and not words[0].startswith("#"):
            fields[words[0].upper()], lines[words[0].upper()] = words[1:], number
    names = fields.get("FIELDS", [])
    n = len(names)
    sizes = [int(s) for s in fields.get("SIZE", ["4"] * n)]
    types = [t.upper() for t in fields.get("TYPE", ["F"] * n)]
    counts = [int(c) for c in fields.get("COUNT", ["1"] * n)]
    if not len(sizes) == len(types) == len(counts) == n:
        raise CloudFileError(path, "PCD header's FIELDS, SIZE, TYPE and COUNT disagree in length")
    width, height = int(fields.get("WIDTH", ["0"])[0]), int(fields.get("HEIGHT", ["1"])[0])
    count = int(fields.get("POINTS", [str(width * height)])[0])
    data = (fields.get("DATA") or ["?"])[0].lower()
    return _PcdLayout(header, lines, names, sizes, types, counts, count, data, offset)


def _pcd_record(path: str, layout: _PcdLayout) -> np.dtype:
    """One point of a binary PCD file, its fields named ``{name}_{index}`` (names may repeat: ``_`` pads)."""
    try:
        return np.dtype([(f"{name}_{i}", "<" + _PCD_TYPES[(t, s)], (k,)) for i, (name, t, s, k) in
                         enumerate(zip(layout.names, layout.types, layout.sizes, layout.counts))])
    except KeyError:
        raise CloudFileError(path, f"unsupported PCD TYPE/SIZE {list(zip(layout.types, layout.sizes))}") from None


def _read_pcd(path: str, select) -> tuple[np.ndarray, int]:
    layout = _pcd_layout(path)
    names, sizes, types, counts, count, data, offset = layout[2:]
    cols = _columns(path, names)
    if any(counts[c] != 1 for c in cols):
        raise CloudFileError(path, "PCD x/y/z fields must have COUNT 1")
    if data == "ascii":
        with open(path, "rb") as f:
            f.seek(offset)
            table = np.loadtxt(f, dtype=np.float64, ndmin=2)
        if table.size == 0:
            table = np.zeros((0, sum(counts)))
        if table.shape[0] != count:
            raise CloudFileError(path, f"PCD header says {count} points, the data has {table.shape[0]}")
        starts = np.cumsum([0] + counts)[:-1]
        rows_kept = select(count)
        table = table if rows_kept is None else table[rows_kept]
        return table[:, [starts[c] for c in cols]], count
    if data == "binary":
        table = _binary_records(path, _pcd_record(path, layout), offset, count, select,
                                "PCD file ends before its {} points")
    elif data == "binary_compressed":
        table = _pcd_compressed_table(path, layout)
        rows_kept = select(count)
        table = table if rows_kept is None else table[rows_kept]
    else:
        raise CloudFileError(path, f"unknown PCD DATA type {data!r}")
    return np.stack([table[f"{names[c]}_{c}"][:, 0].astype(np.float64) for c in cols], axis=1), count


def _pcd_compressed_table(path: str, layout: _PcdLayout) -> np.ndarray:
    """The points (count,) of a ``DATA binary_compressed`` PCD file (what PCL and Open3D write compressed), as
    :func:`_pcd_record` records.

    After the header: the compressed and the decompressed size (uint32 each), then LZF-compressed data that
    holds each field's values for all points in turn (field by field, not point by point).
    """
    record, count = _pcd_record(path, layout), layout.count
    with open(path, "rb") as f:
        f.seek(layout.offset)
        sizes_raw = f.read(8)
        if len(sizes_raw) < 8:
            raise CloudFileError(path, "PCD file ends before its compressed data")
        packed, unpacked = np.frombuffer(sizes_raw, "<u4")
        data = f.read(int(packed))
    if len(data) < packed:
        raise CloudFileError(path, f"PCD file ends before its {packed} bytes of compressed data")
    if unpacked != count * record.itemsize:
        raise CloudFileError(path, f"PCD header says {count} points of {record.itemsize} bytes, the compressed "
                                   f"data holds {unpacked} bytes")
    raw = _lzf_decompress(data, int(unpacked), path)
    table, start = np.zeros(count, record), 0
    for name in record.names:
        field = record.fields[name][0]
        table[name] = np.frombuffer(raw, field.base, count * field.shape[0], start).reshape(count, -1)
        start += count * field.itemsize
    return table


def _lzf_decompress(data: bytes, size: int, path: str) -> bytes:
    """LZF-decompresses ``data`` into exactly ``size`` bytes (liblzf's format, in pure Python; its time
    grows with how many short repeats the data hold).

    The stream is a sequence of tokens, each opened by a control byte: below 32, a literal run of that many
    bytes plus one; otherwise a back reference whose length (plus two) is the top three bits, extended by one
    more byte where they are all set, and whose distance (minus one) is the low five bits followed by a byte.
    """
    out = bytearray()
    pos, end = 0, len(data)
    try:
        while pos < end:
            ctrl = data[pos]
            pos += 1
            if ctrl < 32:
                if pos + ctrl + 1 > end:
                    raise IndexError
                out += data[pos:pos + ctrl + 1]
                pos += ctrl + 1
                continue
            length = ctrl >> 5
            if length == 7:
                length += data[pos]
                pos += 1
            start = len(out) - ((ctrl & 0x1F) << 8) - data[pos] - 1
            pos += 1
            length += 2
            if start < 0:
                raise IndexError
            if len(out) - start >= length:
                out += out[start:start + length]
            else:  # the reference overlaps what it writes: its bytes repeat with the distance as period
                period = out[start:]
                out += (period * (length // len(period) + 1))[:length]
    except IndexError:
        raise CloudFileError(path, "PCD compressed data is corrupt") from None
    if len(out) != size:
        raise CloudFileError(path, f"PCD compressed data unpacks to {len(out)} bytes, not {size}")
    return bytes(out)


_SEPARATOR = re.compile(r"[,\s;]+")


def _is_header(values: list[str]) -> bool:
    """Whether a text file's first line is a header: column names (not all numbers) or a lone point count."""
    values = [v for v in values if v]  # a trailing separator leaves an empty value
    try:
        [float(v) for v in values]
    except ValueError:
        return True
    return len(values) == 1 and values[0].isdigit()


def _read_text(path: str, select) -> tuple[np.ndarray, int]:
    points = _read_text_fast(path)
    if points is None:
        points = _read_text_by_line(path)
    rows_kept = select(len(points))
    return (points if rows_kept is None else points[rows_kept]), len(points)


def _read_text_fast(path: str) -> np.ndarray | None:
    """The points of a regular text file by NumPy's C parser (five times faster than Python's), or None where
    the file is anything else (a short row, a mixed separator, bad bytes): the line-by-line reader then reads
    it or says which line is wrong."""
    try:
        with open(path, "r", encoding="utf-8", errors="strict") as f:
            lines = (line.split("#", 1)[0].strip() for line in f)
            numbered = ((number, line) for number, line in enumerate(lines, 1) if line)
            number, line = next(numbered, (0, ""))
            skip = number - 1
            if line and _is_header(_SEPARATOR.split(line)):
                skip = number
                line = next(numbered, (0, ""))[1]  # the separator is the data's, not the header's
        if not line:
            return np.zeros((0, 3))
        delimiter = "," if "," in line else ";" if ";" in line else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": the line-by-line reader decides
            points = np.loadtxt(path, dtype=np.float64, comments="#", delimiter=delimiter, skiprows=skip,
                                usecols=(0, 1, 2), ndmin=2, encoding="utf-8")
    except (ValueError, UnicodeDecodeError, IndexError):
        return None
    return points


def _read_text_by_line(path: str) -> np.ndarray:
    rows, first = [], True
    with open(path, "r", encoding="utf-8", errors="strict") as f:
        for number, line in enumerate(f, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            values = _SEPARATOR.split(line)
            if first:
                first = False
                if _is_header(values):
                    continue
            if len(values) < 3:
                raise CloudFileError(path, f"not three coordinates: line {number} has {len(values)} value(s)")
            try:
                rows.append([float(v) for v in values[:3]])
            except ValueError:
                raise CloudFileError(path, f"line {number} is not numbers: {line[:60]!r}") from None
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def _read_npy(path: str, select) -> tuple[np.ndarray, int]:
    array = np.load(path, mmap_mode="r", allow_pickle=False)
    if array.ndim != 2 or array.shape[1] != 3:
        raise CloudFileError(path, f"not three coordinates: expected an (N, 3) array, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise CloudFileError(path, f"expected real numbers, got dtype {array.dtype}")
    rows_kept = select(len(array))
    return np.asarray(array if rows_kept is None else array[rows_kept], dtype=np.float64), len(array)


# ------------------------------------------------------------------------------------------------ meshes


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The vertices and triangles of an .obj, .off, .stl or .ply (ASCII or binary) mesh.

    Polygons are split into triangle fans; OBJ's texture and normal indices, groups and materials, OFF's
    colours and PLY's other properties and elements are ignored.

    Returns:
      vertices: (V, 3) float64.
      triangles: (F, 3) int64 indices into ``vertices`` (F may be 0: an OBJ or PLY file of vertices alone).

    Raises:
      CloudFileError: the file is missing, unreadable, of another format, malformed, or a face names a vertex
        it does not have.
    """
    path = os.fspath(path)
    ext = file_format(path, kind="mesh format", formats=MESH_FORMATS)
    if not os.path.isfile(path):
        raise CloudFileError(path, "no such file" if not os.path.exists(path) else "is not a file")
    reader = {".obj": _read_obj, ".off": _read_off, ".stl": _read_stl, ".ply": _read_ply_mesh}[ext]
    try:
        vertices, triangles = reader(path)
    except CloudFileError:
        raise
    except (OSError, ValueError, IndexError, UnicodeDecodeError) as err:
        raise CloudFileError(path, f"unreadable {ext[1:].upper()} file ({_first_line(err)})") from None
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if triangles.size and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise CloudFileError(path, f"a face names a vertex the file does not have (it has {len(vertices)})")
    return vertices, triangles


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, n: int, *, seed: int = 0) -> np.ndarray:
    """``n`` points uniformly distributed over a triangle mesh's surface area.

    Args:
      vertices: (V, 3).
      triangles: (F, 3) vertex indices, F >= 1.
      n: how many points.
      seed: seeds the choice of triangles (by area) and the points within them.

    Returns:
      (n, 3) float64 points.

    Raises:
      ValueError: the triangles have no area (every one degenerate) or a non-finite one.
    """
    vertices = np.asarray(vertices, np.float64)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if not np.isfinite(area).all():
        raise ValueError("the mesh has triangles with NaN or Inf vertices")
    if not area.sum() > 0:
        raise ValueError(f"the mesh's {len(triangles)} triangles have no area")
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(triangles), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    outside = u + v > 1  # reflect into the triangle rather than draw again, so each triangle is filled evenly
    u, v = np.where(outside, 1 - u, u), np.where(outside, 1 - v, v)
    return a[chosen] + u[:, None] * (b - a)[chosen] + v[:, None] * (c - a)[chosen]


def _read_mesh_as_points(path: str, select, n_samples: int, seed: int) -> tuple[np.ndarray, int]:
    vertices, triangles = read_mesh(path)
    if not len(vertices):
        raise CloudFileError(path, "the mesh has no vertices")
    if not len(triangles):  # an OBJ point cloud
        rows_kept = select(len(vertices))
        return (vertices if rows_kept is None else vertices[rows_kept]), len(vertices)
    try:
        return sample_surface(vertices, triangles, n_samples, seed=seed), n_samples
    except ValueError as err:
        raise CloudFileError(path, str(err)) from None


#: The characters ``str.split`` splits on that are ASCII (UTF-8 encodes every other one in several bytes).
_ASCII_SPACE = np.isin(np.arange(256), [9, 10, 11, 12, 13, 28, 29, 30, 31, 32])


def _row_words(rows: list[str]) -> tuple[list[str], np.ndarray]:
    """The words of text rows (as ``str.split`` finds them), all in one list, and (R + 1,) offsets: row r's
    words are ``words[offsets[r]:offsets[r + 1]]``.

    Splitting all rows at once and counting each row's words on its bytes is what makes the text mesh readers
    and :func:`move_file` fast on large meshes: splitting row by row makes a list per row, several times slower.
    """
    text = "\n".join(rows)
    words = text.split()
    raw = np.frombuffer(text.encode("utf-8", errors="surrogateescape"), np.uint8)
    space = _ASCII_SPACE[raw]
    first = np.flatnonzero(~space & np.concatenate([[True], space[:-1]]))  # the first byte of each word
    row = np.searchsorted(np.flatnonzero(raw == 10), first)  # newlines before it
    counts = np.bincount(row, minlength=len(rows))
    # A row with a newline of its own, or a space outside ASCII (which str.split splits on), is counted again
    # row by row: either way the byte count disagrees with the words found.
    if len(counts) != len(rows) or counts.sum() != len(words):
        counts = np.fromiter(map(len, map(str.split, rows)), np.int64, len(rows))
    return words, np.concatenate([[0], np.cumsum(counts)])


def _picked(words: list[str], index: np.ndarray) -> list[str]:
    """``words`` at ``index`` (any shape), flattened."""
    return [words[i] for i in np.ravel(index).tolist()]


def _floats(words: list[str]) -> np.ndarray:
    return np.fromiter(map(float, words), np.float64, len(words))


def _ints(words: list[str]) -> np.ndarray:
    return np.fromiter(map(int, words), np.int64, len(words))


def _leading_xyz(words: list[str], offsets: np.ndarray) -> np.ndarray:
    """(R, 3) floats: the first three words of each row (see :func:`_row_words`; each row holds at least three)."""
    return _floats(_picked(words, offsets[:-1, None] + np.arange(3))).reshape(-1, 3)


def _fans(corners: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(F, 3) triangles splitting each polygon (``counts[i]`` consecutive entries of ``corners``) into a fan."""
    per_polygon = np.maximum(counts - 2, 0)  # a "face" of one or two corners has no area: nothing
    polygon = np.repeat(np.arange(len(counts)), per_polygon)
    first = (np.cumsum(counts) - counts)[polygon]
    step = np.arange(len(polygon)) - (np.cumsum(per_polygon) - per_polygon)[polygon] + 1
    return np.stack([corners[first], corners[first + step], corners[first + step + 1]], axis=1)


def _read_obj(path: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        text = f.read()
    if "#" in text:
        text = re.sub(r"#[^\n]*", "", text)
    # Texture coordinates, normals, groups, materials, lines and blank lines are skipped; vertices and faces
    # keep their order, which negative (relative) indices need.
    rows = re.findall(r"^([vf])[ \t]([^\n]*)", text, re.MULTILINE)
    is_vertex = np.fromiter((kind == "v" for kind, _ in rows), bool, len(rows))
    vertex_words, vertex_offsets = _row_words([row for kind, row in rows if kind == "v"])
    short = np.flatnonzero(np.diff(vertex_offsets) < 3)
    if len(short):
        line = text.count("\n", 0, list(re.finditer(r"^v[ \t]", text, re.MULTILINE))[short[0]].start()) + 1
        raise CloudFileError(path, f"line {line}: a vertex needs three coordinates")
    vertices = _leading_xyz(vertex_words, vertex_offsets)
    faces = [row for kind, row in rows if kind == "f"]
    if any("/" in face for face in faces):  # "v/vt/vn": the vertex
        faces = re.sub(r"(?<=\S)/\S*", "", "\n".join(faces)).split("\n")
    face_words, face_offsets = _row_words(faces)
    counts = np.diff(face_offsets)
    corners = _ints(face_words)
    defined = np.repeat(np.cumsum(is_vertex)[~is_vertex], counts)  # vertices defined before each face
    # 1-based, or negative: counted back from the last vertex defined before the face
    corners = np.where(corners > 0, corners - 1, defined + corners)
    if ((corners < 0) | (corners >= defined)).any():  # index 0 lands here too: defined + 0
        raise CloudFileError(path, "a face names a vertex not defined before it")
    return vertices, _fans(corners, counts)


def _off_layout(path: str, text_lines: list[str]) -> tuple[list[int], list[int]]:
    """Where an OFF file's vertices and faces are: the indices (into ``text_lines``) of its vertex lines and of
    its face lines (comments and blank lines are skipped; a comment after data on a line is not data)."""
    code = [line.partition("#")[0] for line in text_lines] if any("#" in line for line in text_lines) else text_lines
    data = [i for i, line in enumerate(code) if not line.isspace() and line]
    head = code[data[0]].split() if data else []
    keyword = re.fullmatch(r"(ST)?C?N?OFF(.*)", head[0], re.IGNORECASE) if data else None
    if keyword is None:
        raise CloudFileError(path, "not an OFF file (no OFF header)" if not data or "OFF" not in head[0]
                             else f"OFF variant {head[0]!r} is not supported")
    # Counts follow the keyword on its line (ModelNet's files even write "OFF490 518 0"), or on the next.
    counts = ([keyword[2]] if keyword[2] else []) + head[1:]
    body = data[1:]
    if not counts and body:
        counts, body = code[body[0]].split(), body[1:]
    if len(counts) < 2:
        raise CloudFileError(path, "OFF header without vertex and face counts")
    n_vertices, n_faces = int(counts[0]), int(counts[1])
    if len(body) < n_vertices + n_faces:
        raise CloudFileError(path, f"OFF file ends before its {n_vertices} vertices and {n_faces} faces")
    return body[:n_vertices], body[n_vertices:n_vertices + n_faces]


def _read_off(path: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        lines = f.readlines()
    vertex_lines, face_lines = _off_layout(path, lines)
    code = lambda numbers: [lines[i].partition("#")[0] for i in numbers]  # noqa: E731
    vertex_words, vertex_offsets = _row_words(code(vertex_lines))
    if (np.diff(vertex_offsets) < 3).any():
        raise CloudFileError(path, "an OFF vertex has fewer than three coordinates")
    vertices = _leading_xyz(vertex_words, vertex_offsets)
    face_words, face_offsets = _row_words(code(face_lines))
    sizes = _ints(_picked(face_words, face_offsets[:-1]))
    if (np.diff(face_offsets) <= sizes).any() or (sizes < 0).any():
        raise CloudFileError(path, "an OFF face lists fewer corners than its count")
    # a face's colour, if any, follows its corners on its line
    ramp = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    corners = _ints(_picked(face_words, np.repeat(face_offsets[:-1] + 1, sizes) + ramp))
    return vertices, _fans(corners, sizes)


# ASCII STL lines that hold a corner ("vertex x y z") or a normal ("facet normal x y z"), indented or not. Where
# lines are found in a file read without newline translation, a match starts at the end of the line before it
# ("\n", or a "\r" of its own: old Mac files end lines so), which is faster than a look-behind.
_STL_VERTEX_ROW = re.compile(r"^[^\S\n]*vertex(?![^\s])([^\n]*)", re.MULTILINE | re.IGNORECASE)
_STL_COORDINATE_LINE = re.compile(r"[\r\n][^\S\r\n]*(?:vertex|facet)(?![^\s])", re.IGNORECASE)
_STL_RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])


def _stl_is_ascii(path: str) -> bool:
    """Binary STL files have exactly 84 + 50 * count bytes (some also open with "solid"); ASCII ones do not."""
    with open(path, "rb") as f:
        head = f.read(84)
    count = int(np.frombuffer(head[80:84], "<u4")[0]) if len(head) == 84 else -1
    return not (count >= 0 and os.path.getsize(path) == 84 + 50 * count)


def _read_stl(path: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "rb") as f:
        head = f.read(84)
    if not _stl_is_ascii(path):
        count = int(np.frombuffer(head[80:84], "<u4")[0])
        corners = np.fromfile(path, _STL_RECORD, count=count, offset=84)["corners"].reshape(-1, 3)
    elif head.lstrip().lower().startswith(b"solid"):
        with open(path, "r", encoding="ascii", errors="replace") as f:
            rows = _STL_VERTEX_ROW.findall(f.read())
        if len(rows) % 3:
            raise CloudFileError(path, f"ASCII STL with {len(rows)} vertices, not three per facet")
        words, offsets = _row_words(rows)
        if (np.diff(offsets) < 3).any():
            raise CloudFileError(path, "an STL vertex has fewer than three coordinates")
        corners = _leading_xyz(words, offsets)
    else:
        raise CloudFileError(path, "not an STL file (neither 'solid' text nor a binary file of its size)")
    # STL repeats each corner in every facet that uses it; sampling needs no shared vertices
    return corners.astype(np.float64), np.arange(len(corners)).reshape(-1, 3)


# ----------------------------------------------------------------------------------------------- writers


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _text_format(points: np.ndarray) -> str:
    return "%.17g" if points.dtype == np.float64 else "%.9g"  # enough digits to read back the same value


def _write_ply(f, points: np.ndarray, binary: bool) -> None:
    kind = "double" if points.dtype == np.float64 else "float"
    fmt = "binary_little_endian" if binary else "ascii"
    header = (f"ply\nformat {fmt} 1.0\ncomment written by dit-jax\nelement vertex {len(points)}\n"
              f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n")
    f.write(header.encode("ascii"))
    if binary:
        f.write(np.ascontiguousarray(points, dtype="<f8" if kind == "double" else "<f4").tobytes())
    else:
        np.savetxt(f, points, fmt=_text_format(points))


def _write_pcd(f, points: np.ndarray, binary: bool) -> None:
    # float32 whatever the input: PCL's convention, and Open3D 0.20 reads binary SIZE 8 fields as zeros.
    points = np.asarray(points, np.float32)
    size, dtype = 4, "<f4"
    header = (f"# .PCD v0.7 - written by dit-jax\nVERSION 0.7\nFIELDS x y z\nSIZE {size} {size} {size}\n"
              f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {len(points)}\nDATA {'binary' if binary else 'ascii'}\n")
    f.write(header.encode("ascii"))
    if binary:
        f.write(np.ascontiguousarray(points, dtype=dtype).tobytes())
    else:
        np.savetxt(f, points, fmt=_text_format(points))
