"""LAS and LAZ files (laspy, with lazrs for LAZ): read and moved, damaged headers and chunk tables refused."""

from __future__ import annotations

import io as io_lib
import os
import struct

import numpy as np

from dit_jax.io.common import CloudFileError, _first_line


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
