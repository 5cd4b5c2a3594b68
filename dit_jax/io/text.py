"""Text clouds (.xyz, .txt, .csv, .asc, .pts) and NPY arrays: read."""

from __future__ import annotations

import re
import warnings

import numpy as np

from dit_jax.io.common import CloudFileError

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
