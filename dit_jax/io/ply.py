"""PLY files (plyfile): clouds and triangle meshes read, clouds written, files moved."""

from __future__ import annotations

import io as io_lib
import warnings

import numpy as np

from dit_jax.io.common import _NORMALS, _XYZ, CloudFileError, _columns, _fans, _first_line, _move_fields

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
