"""dit_jax.io.read on malformed files of every format it takes: finite points or a CloudFileError naming the
file, nothing else, and no file left behind."""

import os

import numpy as np
import pytest

from dit_jax import io

#: Files per run (seeded: the same files every run).
CASES = 240


def _valid_files(folder, rng) -> list:
    """One valid file of each format io.read takes, small, in ``folder``."""
    cloud = rng.normal(size=(40, 3)) * 3.0 + 10.0
    files = []
    for ext in io.WRITE_FORMATS:
        for binary in (True, False) if ext in (".ply", ".pcd") else (True,):
            path = folder / f"valid_{'b' if binary else 'a'}{ext}"
            io.write(path, cloud, binary=binary) if ext in (".ply", ".pcd") else io.write(path, cloud)
            files.append(path)
    import laspy

    for ext in (".las", ".laz"):
        las = laspy.create(point_format=0, file_version="1.2")
        las.header.scales, las.header.offsets = [0.001] * 3, [0.0] * 3
        las.x, las.y, las.z = cloud.T
        path = folder / f"valid{ext}"
        las.write(str(path))
        files.append(path)
    triangles = "\n".join(f"f {a} {a + 1} {a + 2}" for a in range(1, 38, 3))
    (folder / "valid.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in cloud) + triangles + "\n")
    (folder / "valid.off").write_text(
        "OFF\n40 13 0\n"
        + "".join(f"{x} {y} {z}\n" for x, y, z in cloud)
        + "".join(f"3 {a} {a + 1} {a + 2}\n" for a in range(0, 37, 3))
    )
    facets = "".join(
        "facet normal 0 0 1\nouter loop\n"
        + "".join(f"vertex {x} {y} {z}\n" for x, y, z in cloud[a : a + 3])
        + "endloop\nendfacet\n"
        for a in range(0, 37, 3)
    )
    (folder / "valid.stl").write_text(f"solid s\n{facets}endsolid s\n")
    return files + [folder / "valid.obj", folder / "valid.off", folder / "valid.stl"]


def _mutant(data: bytes, rng) -> bytes:
    """One malformed version of a file's bytes: cut, bytes flipped, counts lying, NaN or Inf, huge or tiny
    numbers, or random bytes."""
    kind = rng.integers(7)
    if kind == 0:  # truncated at a random offset
        return data[: rng.integers(len(data))]
    if kind == 1:  # random bytes overwritten
        array = bytearray(data)
        for at in rng.integers(0, len(data), rng.integers(1, 20)):
            array[at] = rng.integers(256)
        return bytes(array)
    if kind == 2:  # a number in the header or the text made larger or smaller (counts that lie)
        text = data.decode("latin-1")
        digits = [i for i, c in enumerate(text[:400]) if c.isdigit()]
        if digits:
            at = digits[rng.integers(len(digits))]
            text = text[:at] + str(rng.choice([0, 1, 7, 1000, 2_000_000_000])) + text[at + 1 :]
        return text.encode("latin-1")
    if kind == 3:  # NaN, Inf, huge and tiny values in place of numbers
        text = data.decode("latin-1")
        word = str(rng.choice(["nan", "inf", "-inf", "1e308", "1e-320", "1e400"]))
        at = rng.integers(len(text))
        return (text[:at] + " " + word + " " + text[at:]).encode("latin-1")
    if kind == 4:  # random bytes of the file's length
        return rng.integers(0, 256, len(data), dtype=np.uint8).tobytes()
    if kind == 5:  # empty
        return b""
    return data + rng.integers(0, 256, rng.integers(1, 64), dtype=np.uint8).tobytes()  # trailing junk


def test_every_malformed_file_reads_to_finite_points_or_a_named_error(tmp_path):
    rng = np.random.default_rng(0)
    valid = tmp_path / "valid"
    valid.mkdir()
    sources = _valid_files(valid, rng)
    for source in sources:
        points = io.read(source)
        assert points.shape[1] == 3 and np.all(np.isfinite(points)), source
    cases = tmp_path / "cases"
    cases.mkdir()
    outcomes = {"read": 0, "refused": 0}
    for k in range(CASES):
        source = sources[k % len(sources)]
        path = cases / f"case_{k}{source.suffix}"
        path.write_bytes(_mutant(source.read_bytes(), rng))
        try:
            points = io.read(path, max_points=5_000, mesh_points=500)
        except io.CloudFileError as err:
            assert str(err).startswith(str(path)), (path, err)
            outcomes["refused"] += 1
        except Exception as err:  # noqa: BLE001 - the very thing this test forbids
            pytest.fail(f"{path} ({source.name}): {type(err).__name__}: {err}")
        else:
            assert points.ndim == 2 and points.shape[1] == 3 and points.dtype == np.float64, path
            assert np.all(np.isfinite(points)), path
            outcomes["read"] += 1
    assert sorted(os.listdir(cases)) == sorted(f"case_{k}{sources[k % len(sources)].suffix}" for k in range(CASES))
    assert outcomes["refused"] > CASES // 4  # the mutations do break most files
