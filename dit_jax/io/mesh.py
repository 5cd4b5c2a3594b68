"""Meshes (.obj, .off, .stl, and PLY files with faces): read, sampled over their surface, moved line by line."""

from __future__ import annotations

import itertools
import os
import re

import numpy as np

from dit_jax.io.common import MESH_FORMATS, CloudFileError, _fans, _first_line, file_format
from dit_jax.io.ply import _read_ply_mesh


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


def _moved_binary_stl(path: str, rotation: np.ndarray, translation: np.ndarray) -> bytes:
    """The bytes of binary STL file ``path`` with its facets' corners moved and their normals turned; its header
    and attribute words kept."""
    read_mesh(path)  # refuses a malformed file first
    with open(path, "rb") as f:
        head, records = f.read(84), np.frombuffer(f.read(), _STL_RECORD).copy()
    records["corners"] = records["corners"].astype(np.float64) @ rotation.T + translation
    records["normal"] = records["normal"].astype(np.float64) @ rotation.T
    return head + records.tobytes()
