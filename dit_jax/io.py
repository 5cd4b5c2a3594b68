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

import contextlib
import io as io_lib
import itertools
import os
import re
import stat
import struct
import tempfile
import tokenize
import warnings

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


def file_format(path: str | os.PathLike, kind: str = "format", formats: tuple[str, ...] = FORMATS) -> str:
    """The lower-case extension of ``path`` if it is one of ``formats``, else :class:`CloudFileError`."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in formats:
        raise CloudFileError(path, f"unknown {kind} {ext or '(no extension)'!r}; expected one of {', '.join(formats)}")
    return ext


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
    if not os.path.exists(path):
        raise CloudFileError(path, "no such file")
    if os.path.isdir(path):
        raise CloudFileError(path, "is a directory, not a point-cloud file")
    if not stat.S_ISREG(os.stat(path).st_mode):  # a pipe would block for ever, a device never end
        raise CloudFileError(path, "is not a regular file (a pipe, socket or device)")
    if not os.access(path, os.R_OK):
        raise CloudFileError(path, "permission denied")
    if mesh_points < 1:
        raise ValueError(f"mesh_points must be positive, got {mesh_points}")
    n_samples = mesh_points if max_points is None else min(mesh_points, max_points)
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
    content = None  # the moved file, made whole before anything is written
    try:
        if ext == ".ply":
            content = _moved_ply(source, rotation, translation)
        elif ext == ".pcd":
            content = _moved_pcd(source, rotation, translation)
        elif ext in (".las", ".laz"):
            content = _moved_las(source, rotation, translation)
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
        out.write(content)


def _moved_ply(path: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of PLY file ``path`` (plyfile) with its vertices' x, y, z moved and nx, ny, nz turned; its other
    properties, elements, comments and format kept."""
    ply = _ply(path)
    data = np.array(_ply_vertices(path, ply))
    if any(data.dtype[axis].kind != "f" for axis in _XYZ):
        raise CloudFileError(
            path,
            "PLY coordinates stored as integers would be rounded when moved; "
            "write the moved points to another file instead",
        )
    _move_fields(data, _NORMALS[".ply"], rotation, translation)
    ply["vertex"].data = data
    buffer = io_lib.BytesIO()
    ply.write(buffer)
    content = buffer.getvalue()
    with open(path, "rb") as f:
        crlf = f.readline().endswith(b"\r\n")
    if crlf:  # plyfile writes "\n"; a file whose lines end in "\r\n" keeps them (the header's, in a binary one)
        end = content.index(b"end_header\n") + len(b"end_header\n")
        header, body = content[:end], content[end:]
        content = header.replace(b"\n", b"\r\n") + (body.replace(b"\n", b"\r\n") if ply.text else body)
    return content


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


def _moved_las(path: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of LAS or LAZ file ``path`` (laspy) with X, Y, Z moved at the file's scale (its stated
    precision), the header's bounds (and, where the moved points would overflow its integers, its offset)
    updated; every other attribute, record and VLR kept, LAZ compressed again."""
    las = _las(path)
    moved = np.asarray(las.xyz, np.float64) @ rotation.T + translation
    scale, offset = np.asarray(las.header.scales, np.float64), np.asarray(las.header.offsets, np.float64)
    limit = 2**31 - 2**20  # int32, with room for rounding
    if len(moved) and (np.abs((moved - offset) / scale) > limit).any():
        # re-centre the integers on the moved points
        # (the header's offset alone: the points are all assigned anew below)
        las.header.offsets = np.round((moved.min(axis=0) + moved.max(axis=0)) / 2 / scale) * scale
    las.x, las.y, las.z = moved.T
    las.update_header()
    buffer = io_lib.BytesIO()
    las.write(buffer, do_compress=path.lower().endswith(".laz"))
    return buffer.getvalue()


def _move_fields(
    table: np.ndarray, normals: tuple[str, str, str], rotation: np.ndarray, translation: np.ndarray
) -> None:
    """Moves x, y, z of a structured array of points in place, and turns its normals where it has them."""
    names = table.dtype.names
    groups = [(axes, axes is not _XYZ) for axes in (_XYZ, normals) if all(a in names for a in axes)]
    _move_columns([([table[a] for a in axes], is_normal) for axes, is_normal in groups], rotation, translation)


def _moved_text_mesh(path: str, ext: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of an OBJ, OFF or ASCII STL file with its vertices moved and its normals turned: each such line
    is written again as its words joined by single spaces, a comment at its end and its line end kept."""
    with open(path, encoding="utf-8", errors="surrogateescape", newline="") as f:  # "\r\n" stays
        lines = f.readlines()
    numbers = _mesh_coordinate_lines(path, ext, lines)
    rows = [lines[n].rstrip("\r\n") for n in numbers]
    tails = [lines[n][len(row) :] for n, row in zip(numbers, rows)]  # the line ends
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


def _move_columns(groups: list[tuple[list[np.ndarray], bool]], rotation: np.ndarray, translation: np.ndarray) -> None:
    """Moves each group of three coordinate columns (views into a file's records, (N,) each) in place, or,
    where the group is a normal, turns it."""
    for views, is_normal in groups:
        values = np.stack([view.astype(np.float64) for view in views], axis=1) @ rotation.T
        for view, column in zip(views, (values if is_normal else values + translation).T):
            view[...] = column


_XYZ = ("x", "y", "z")
_NORMALS = {".ply": ("nx", "ny", "nz"), ".pcd": ("normal_x", "normal_y", "normal_z")}


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


def _columns(path: str, names: list[str]) -> list[int]:
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise CloudFileError(
            path, f"not three coordinates: no {'/'.join(missing)} field (fields: {' '.join(names) or 'none'})"
        )
    return [names.index(axis) for axis in "xyz"]


#: What plyfile may assume of a mesh's face lists: three corners each (it checks, and the read falls back).
_TRIANGLE_LISTS = {"face": {"vertex_indices": 3, "vertex_index": 3}}


def _ply(path: str, *, mmap: bool = False):
    """The ``plyfile.PlyData`` of a PLY file, binary elements memory-mapped: read-only with ``mmap``, else
    copy-on-write (plyfile's unmapped read goes row by row, hundreds of times slower)."""
    from plyfile import PlyData, PlyParseError

    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise CloudFileError(path, "not a PLY file (first line is not 'ply')")
    try:
        try:  # triangle meshes read as one array, not a Python list per face (a hundred times faster)
            return PlyData.read(path, mmap="r" if mmap else "c", known_list_len=_TRIANGLE_LISTS)
        except PlyParseError:
            pass  # not all triangles (or malformed: the plain read says what is wrong)
        return PlyData.read(path, mmap="r" if mmap else "c")
    except PlyParseError as err:
        raise CloudFileError(path, f"malformed PLY file ({_first_line(err)})") from None


def _ascii_ply_vertices(path: str) -> tuple[np.ndarray, list[str]] | None:
    """The vertex rows ``(N, P)`` and property names of an ASCII PLY file whose first element is its vertices,
    all scalar, and which has no faces; None for any other file (``_ply`` reads those).

    plyfile parses ASCII PLY row by row with a ``numpy.loadtxt`` call per row, and reads every element, so a
    range scan's vertices took seconds behind their scan-grid lists; NumPy's loader reads the vertex block in
    one call.
    """
    # (name, count, [(property, declared float32), ...]); a list property is (None, False): not for this path
    elements: list[tuple[str, int, list[tuple[str | None, bool]]]] = []
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply" or f.readline().split() != [b"format", b"ascii", b"1.0"]:
            return None
        for line in f:
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "element" and len(words) == 3 and words[2].isdigit():
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements and len(words) == 3:
                elements[-1][2].append((words[2], words[1] in ("float", "float32")))
            elif words[0] == "property" and elements and words[1:2] == ["list"]:
                elements[-1][2].append((None, False))
            else:
                return None
        else:
            return None
        if not elements or elements[0][0] != "vertex" or any(name is None for name, _ in elements[0][2]):
            return None
        if any(name == "face" and count for name, count, _ in elements):
            return None
        _, count, properties = elements[0]
        names = [name for name, _ in properties]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # an empty vertex block
                rows = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2, comments=None)
        except ValueError:
            return None
    if rows.shape != (count, len(names)) and not (count == 0 and rows.size == 0):
        return None
    rows = rows.reshape(count, len(names))
    single = np.array([is_single for _, is_single in properties], bool)
    rows[:, single] = rows[:, single].astype(np.float32)  # rounded as plyfile's read rounds them
    return rows, names


def _ply_vertices(path: str, ply) -> np.ndarray:
    """The vertex element's records of a ``PlyData`` (x, y and z among their fields)."""
    if "vertex" not in ply:
        raise CloudFileError(path, "PLY file has no vertex element")
    data = ply["vertex"].data
    _columns(path, list(data.dtype.names or ()))
    return data


def _ply_triangles(ply) -> np.ndarray | None:
    """(F, 3) triangles of a ``PlyData``'s faces (polygons split into fans), or None where it has none."""
    if "face" not in ply or not ply["face"].count:
        return None
    names = [prop.name for prop in ply["face"].properties]
    name = next((n for n in ("vertex_indices", "vertex_index") if n in names), None)
    if name is None:
        return None
    lists = ply["face"].data[name]
    if lists.dtype != object:  # read as (F, 3): triangles already
        return np.asarray(lists, np.int64).reshape(-1, 3)
    counts = np.fromiter(map(len, lists), np.int64, len(lists))
    corners = np.concatenate(list(lists)).astype(np.int64) if counts.sum() else np.zeros(0, np.int64)
    return _fans(corners, counts)


def _read_ply(path: str, select, ply=None) -> tuple[np.ndarray, int]:
    """The vertices of a PLY file (``select`` picks the rows kept) and how many it holds."""
    data = _ply_vertices(path, ply if ply is not None else _ply(path, mmap=True))
    rows_kept = select(len(data))
    kept = data if rows_kept is None else data[rows_kept]
    return np.stack([np.asarray(kept[axis], np.float64) for axis in _XYZ], axis=1), len(data)


def _read_ply_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    ply = _ply(path, mmap=True)
    vertices, _ = _read_ply(path, lambda count: None, ply)
    triangles = _ply_triangles(ply)
    return vertices, np.zeros((0, 3), np.int64) if triangles is None else triangles


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


def _las_layout_problem(path: str) -> str | None:
    """What the fixed LAS header says that cannot be (checked before laspy reads it, which would loop over
    every claimed record): points that start past the file's end, more variable-length records than fit
    before them."""
    with open(path, "rb") as f:
        head = f.read(105)
    if len(head) < 105 or head[:4] != b"LASF":
        return None  # laspy says what is wrong
    header_size, points_at, records = struct.unpack_from("<HII", head, 94)
    if points_at > os.path.getsize(path):
        return f"its points start at byte {points_at:,}, past its end"
    if records * 54 > max(points_at - header_size, 0):  # a VLR's own header is 54 bytes
        return f"{records:,} variable-length records claimed before byte {points_at:,}"
    return None


def _laz_chunks_problem(path: str, header) -> str | None:
    """What a LAZ file's chunk table says that cannot be: a table past the file's end, or more chunks than
    points (the decompressor would allocate for every claimed chunk first)."""
    if not header.are_points_compressed:
        return None
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        f.seek(header.offset_to_point_data)
        raw = f.read(8)
        if len(raw) < 8:
            return "no chunk table"
        table = struct.unpack("<q", raw)[0]
        if table == -1:  # not written: the decompressor finds the chunks itself
            return None
        if not header.offset_to_point_data < table <= size - 8:
            return f"its chunk table lies at byte {table:,} of {size:,}"
        f.seek(table)
        _, chunks = struct.unpack("<II", f.read(8))
    if chunks > max(header.point_count, 1):
        return f"{chunks:,} chunks for {header.point_count:,} points"
    return None


#: The most a LAZ file's points may be compressed, as uncompressed bytes per file byte.
LAZ_RATIO = 50


def _lazrs_errors() -> tuple[type[BaseException], ...]:
    """The LAZ decompressor's error type (a corrupt stream), where lazrs is installed."""
    try:
        from lazrs import LazrsError
    except ImportError:
        return ()
    return (LazrsError,)


def _las(path: str):
    """The ``laspy.LasData`` of a LAS or LAZ file."""
    import laspy

    problem = _las_layout_problem(path)
    if problem:
        raise CloudFileError(path, f"malformed {os.path.splitext(path)[1][1:].upper()} file ({problem})")
    try:
        with laspy.open(path) as reader:
            header = reader.header
        problem = _laz_chunks_problem(path, header)
        if problem:
            raise CloudFileError(path, f"malformed LAZ file ({problem})")
        size = header.offset_to_point_data + header.point_count * header.point_format.size
        if not header.are_points_compressed and os.path.getsize(path) < size:
            raise CloudFileError(path, f"LAS file ends before its {header.point_count} points")
        # LAZ packs points about ten times at best: a header claiming far more than that is lying, and reading
        # it would allocate for every claimed point first.
        if header.are_points_compressed and size > LAZ_RATIO * os.path.getsize(path):
            raise CloudFileError(path, f"LAZ header claims {header.point_count:,} points, more than the file holds")
        return laspy.read(path)
    except CloudFileError:
        raise
    except (laspy.LaspyException, ValueError, EOFError, OSError, struct.error, *_lazrs_errors()) as err:
        raise CloudFileError(
            path, f"malformed {os.path.splitext(path)[1][1:].upper()} file ({_first_line(err)})"
        ) from None


def _read_las(path: str, select) -> tuple[np.ndarray, int]:
    """LAS 1.0-1.4 and LAZ (laspy, with lazrs), any point format: X, Y, Z scaled and offset as the header says."""
    las = _las(path)
    rows_kept = select(len(las.points))
    xyz = np.asarray(las.xyz, np.float64)
    return (xyz if rows_kept is None else xyz[rows_kept]), len(las.points)


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
        with open(path, encoding="utf-8", errors="strict") as f:
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
            points = np.loadtxt(
                path,
                dtype=np.float64,
                comments="#",
                delimiter=delimiter,
                skiprows=skip,
                usecols=(0, 1, 2),
                ndmin=2,
                encoding="utf-8",
            )
    except (ValueError, UnicodeDecodeError, IndexError):
        return None
    return points


def _read_text_by_line(path: str) -> np.ndarray:
    rows, first = [], True
    with open(path, encoding="utf-8", errors="strict") as f:
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
    """``n`` points uniformly distributed over a triangle mesh's surface area (``trimesh.sample``).

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
    import trimesh

    vertices = np.asarray(vertices, np.float64)
    mesh = trimesh.Trimesh(vertices, np.asarray(triangles, np.int64), process=False, validate=False)
    area = mesh.area_faces
    if not np.isfinite(area).all():
        raise ValueError("the mesh has triangles with NaN or Inf vertices")
    if not area.sum() > 0:
        raise ValueError(f"the mesh's {len(triangles)} triangles have no area")
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, np.float64)


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
    with open(path, encoding="utf-8", errors="replace") as f:
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
        raise CloudFileError(
            path,
            "not an OFF file (no OFF header)"
            if not data or "OFF" not in head[0]
            else f"OFF variant {head[0]!r} is not supported",
        )
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
    return body[:n_vertices], body[n_vertices : n_vertices + n_faces]


def _read_off(path: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path, encoding="utf-8", errors="replace") as f:
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
    """An STL file's corners and triangles. Read here: binary STL is one NumPy record per facet, and trimesh
    refuses ASCII STL whose lines end in a lone carriage return (old Mac files), which this reads."""
    with open(path, "rb") as f:
        head = f.read(84)
    if not _stl_is_ascii(path):
        count = int(np.frombuffer(head[80:84], "<u4")[0])
        corners = np.fromfile(path, _STL_RECORD, count=count, offset=84)["corners"].reshape(-1, 3)
    elif head.lstrip().lower().startswith(b"solid"):
        with open(path, encoding="ascii", errors="replace") as f:
            rows = _STL_VERTEX_ROW.findall(f.read().replace("\r", "\n"))
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
    """Binary little-endian (or ASCII) PLY through plyfile, double where the points are, else float."""
    from plyfile import PlyData, PlyElement

    kind = "<f8" if points.dtype == np.float64 else "<f4"
    vertex = np.empty(len(points), [(axis, kind) for axis in _XYZ])
    for k, axis in enumerate(_XYZ):
        vertex[axis] = points[:, k]
    PlyData(
        [PlyElement.describe(vertex, "vertex")], text=not binary, byte_order="<", comments=["written by dit-jax"]
    ).write(f)


def _write_pcd(f, points: np.ndarray, binary: bool) -> None:
    """Binary (or ASCII) PCD through pypcd4, in float32 whatever the input: PCL's convention, and Open3D reads
    binary SIZE 8 fields as zeros."""
    from pypcd4 import Encoding, PointCloud

    cloud = PointCloud.from_xyz_points(np.asarray(points, np.float32))
    cloud.save(f, encoding=Encoding.BINARY if binary else Encoding.ASCII)
