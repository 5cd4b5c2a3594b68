"""Point-cloud files: read and write .ply, .pcd, text (.xyz, .txt, .csv, .asc, .pts) and .npy, refusing bad
input with one-line errors.

Every reader returns an (N, 3) float64 array of coordinates and raises :class:`CloudFileError` (a ValueError
whose message names the file and the problem) for anything it cannot turn into one: a missing or unreadable
file, an unknown extension, a malformed header, values that are NaN or Inf, or rows that are not three
coordinates. Formats:

* PLY: ``ascii``, ``binary_little_endian`` and ``binary_big_endian``; the ``x``, ``y``, ``z`` properties of the
  ``vertex`` element (other properties and elements are skipped). Binary files are memory-mapped.
* PCD: ``DATA ascii`` and ``DATA binary`` with fields ``x y z`` (any others skipped). ``binary_compressed`` is
  refused with the hint to re-save as binary.
* Text (.xyz, .txt, .csv, .asc, .pts): one point per line, whitespace, comma or semicolon separated;
  columns after the third (normals, colours, intensity) are ignored, ``#`` starts a comment, and a first
  line that is not three numbers is taken for a header and skipped (column names such as ``x,y,z`` or
  ``//X,Y,Z``, or the point count that opens a .pts file).
* NPY: an (N, 3) array of any real dtype, memory-mapped.

Writers (:func:`write`) produce binary little-endian PLY (float or double as the input), binary float32 PCD
(what PCL and Open3D read), text with enough digits to round-trip (17 for float64, 9 otherwise; .csv
comma-separated under an ``x,y,z`` header, .pts after the point count) and
float32/64 NPY. They write to a temporary file in the destination's folder and rename it into place, so a
failure leaves nothing half-written.
"""

from __future__ import annotations

import os
import re
import tempfile

import numpy as np

FORMATS = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".asc", ".pts", ".npy")
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


def file_format(path: str | os.PathLike, kind: str = "format") -> str:
    """The lower-case extension of ``path`` if it is one of :data:`FORMATS`, else :class:`CloudFileError`."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in FORMATS:
        raise CloudFileError(path, f"unknown {kind} {ext or '(no extension)'!r}; expected one of "
                                   f"{', '.join(FORMATS)}")
    return ext


def read(path: str | os.PathLike, *, max_points: int | None = None, seed: int = 0,
         return_count: bool = False):
    """Reads the points of a .ply, .pcd, text (.xyz, .txt, .csv, .asc, .pts) or .npy file.

    Args:
      path: the file; its extension picks the format.
      max_points: files with more points than this give a uniform random subset of ``max_points`` of them
        (seeded by ``seed``, file order kept); binary PLY/PCD and NPY files never load the other rows.
      return_count: also return how many points the file holds.

    Returns:
      points: (N, 3) float64, all finite; with ``return_count`` the pair ``(points, points_in_file)``.

    Raises:
      CloudFileError: the file is missing, unreadable, of an unknown format, malformed, not three coordinates
        per point, or holds NaN or Inf values.
    """
    path = os.fspath(path)
    ext = file_format(path)
    if not os.path.exists(path):
        raise CloudFileError(path, "no such file")
    if os.path.isdir(path):
        raise CloudFileError(path, "is a directory, not a point-cloud file")
    if not os.access(path, os.R_OK):
        raise CloudFileError(path, "permission denied")
    reader = {".ply": _read_ply, ".pcd": _read_pcd, ".npy": _read_npy}.get(ext, _read_text)
    def select(count: int) -> np.ndarray | None:
        if max_points is None or count <= max_points:
            return None
        return np.sort(np.random.default_rng(seed).choice(count, max_points, replace=False))

    try:
        points, total = reader(path, select)
    except CloudFileError:
        raise
    except (OSError, ValueError, UnicodeDecodeError, EOFError) as err:
        raise CloudFileError(path, f"unreadable {ext[1:].upper()} file ({_first_line(err)})") from None
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise CloudFileError(path, f"expected N x 3 coordinates, got an array of shape {points.shape}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise CloudFileError(path, f"{int(bad.sum())} of {len(points)} points have NaN or Inf coordinates "
                                   f"(first at row {int(np.argmax(bad))})")
    return (points, total) if return_count else points


def write(path: str | os.PathLike, points: np.ndarray, *, binary: bool = True) -> None:
    """Writes (N, 3) points as .ply, .pcd (binary unless ``binary=False``), text or .npy, atomically."""
    path = os.fspath(path)
    ext = file_format(path)
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise CloudFileError(path, f"folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=ext, dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
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


def _read_ply(path: str, select) -> tuple[np.ndarray, int]:
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise CloudFileError(path, "not a PLY file (first line is not 'ply')")
        header = _read_header(f, path, b"end_header")
        offset = f.tell()
    fmt, elements = None, []  # elements: [name, count, [(prop name, dtype or None for lists)]]
    for line in header:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], None))
            elif words[1] in _PLY_TYPES and len(words) == 3:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise CloudFileError(path, f"unsupported PLY property line {line!r}")
        else:
            raise CloudFileError(path, f"malformed PLY header line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise CloudFileError(path, f"unknown PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise CloudFileError(path, "PLY file has no vertex element")
    index = names.index("vertex")
    _, count, props = elements[index]
    prop_names = [p[0] for p in props]
    cols = _columns(path, prop_names)
    if any(dtype is None for _, dtype in props):
        raise CloudFileError(path, "PLY vertex element has list properties; only scalar properties are read")

    if fmt == "ascii":
        skip = sum(e[1] for e in elements[:index])
        with open(path, "rb") as f:
            f.seek(offset)
            for _ in range(skip):
                f.readline()
            rows = [f.readline().decode("ascii") for _ in range(count)]
        if count and not rows[-1]:
            raise CloudFileError(path, f"PLY file ends before its {count} vertices")
        table = np.loadtxt(rows, dtype=np.float64, ndmin=2, usecols=range(len(props)))
        table = table[:, cols] if count else np.zeros((0, 3))
        rows_kept = select(count)
        return (table if rows_kept is None else table[rows_kept]), count

    if any(dtype is None for e in elements[:index] for _, dtype in e[2]):
        raise CloudFileError(path, "PLY elements with list properties come before the vertices")
    order = "<" if fmt == "binary_little_endian" else ">"

    def record(props_):
        return np.dtype([(n if n else f"_{i}", order + t) for i, (n, t) in enumerate(props_)])

    start = offset + sum(e[1] * record(e[2]).itemsize for e in elements[:index])
    table = _binary_records(path, record(props), start, count, select, "PLY file ends before its {} vertices")
    return np.stack([table[axis].astype(np.float64) for axis in "xyz"], axis=1), count


def _read_pcd(path: str, select) -> tuple[np.ndarray, int]:
    with open(path, "rb") as f:
        header = _read_header(f, path, b"DATA")
        offset = f.tell()
    fields: dict[str, list[str]] = {}
    for line in header:
        words = line.split()
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
    names = fields.get("FIELDS", [])
    cols = _columns(path, names)
    n = len(names)
    sizes = [int(s) for s in fields.get("SIZE", ["4"] * n)]
    types = [t.upper() for t in fields.get("TYPE", ["F"] * n)]
    counts = [int(c) for c in fields.get("COUNT", ["1"] * n)]
    if not len(sizes) == len(types) == len(counts) == n:
        raise CloudFileError(path, "PCD header's FIELDS, SIZE, TYPE and COUNT disagree in length")
    width, height = int(fields.get("WIDTH", ["0"])[0]), int(fields.get("HEIGHT", ["1"])[0])
    count = int(fields.get("POINTS", [str(width * height)])[0])
    data = (fields.get("DATA") or ["?"])[0].lower()
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
        try:
            dtype = np.dtype([(f"{name}_{i}", "<" + _PCD_TYPES[(t, s)], (k,)) for i, (name, t, s, k) in
                              enumerate(zip(names, types, sizes, counts))])
        except KeyError:
            raise CloudFileError(path, f"unsupported PCD TYPE/SIZE {list(zip(types, sizes))}") from None
        table = _binary_records(path, dtype, offset, count, select, "PCD file ends before its {} points")
        points = np.stack([table[f"{names[c]}_{c}"][:, 0].astype(np.float64) for c in cols], axis=1)
        return points, count
    if data == "binary_compressed":
        raise CloudFileError(path, "PCD 'DATA binary_compressed' is not supported; re-save it as binary or ascii")
    raise CloudFileError(path, f"unknown PCD DATA type {data!r}")


_SEPARATOR = re.compile(r"[,\s;]+")


def _is_header(values: list[str]) -> bool:
    """Whether a text file's first line is a header: column names (not all numbers) or a lone point count."""
    try:
        [float(v) for v in values]
    except ValueError:
        return True
    return len(values) == 1 and values[0].isdigit()


def _read_text(path: str, select) -> tuple[np.ndarray, int]:
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
    points = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    rows_kept = select(len(points))
    return (points if rows_kept is None else points[rows_kept]), len(points)


def _read_npy(path: str, select) -> tuple[np.ndarray, int]:
    array = np.load(path, mmap_mode="r", allow_pickle=False)
    if array.ndim != 2 or array.shape[1] != 3:
        raise CloudFileError(path, f"not three coordinates: expected an (N, 3) array, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise CloudFileError(path, f"expected real numbers, got dtype {array.dtype}")
    rows_kept = select(len(array))
    return np.asarray(array if rows_kept is None else array[rows_kept], dtype=np.float64), len(array)


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
