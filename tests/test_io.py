"""Point-cloud files: every format read back as written (ours and Open3D's), and every bad file refused."""

from __future__ import annotations

import os

import numpy as np
import pytest

from dit_jax import io


@pytest.fixture
def cloud() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(257, 3)) * [3.0, 0.5, 100.0] + [1000.0, -2.0, 0.25]


@pytest.mark.parametrize("name,binary", [("a.ply", True), ("a.ply", False), ("a.pcd", True), ("a.pcd", False),
                                         ("a.xyz", False), ("a.txt", False), ("a.csv", False), ("a.asc", False),
                                         ("a.pts", False), ("a.npy", True)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_round_trip_every_format(tmp_path, cloud, name, binary, dtype):
    points = cloud.astype(dtype)
    path = tmp_path / name
    io.write(path, points, binary=binary)
    back = io.read(path)
    assert back.shape == points.shape and back.dtype == np.float64
    float32_file = dtype == np.float32 or name.endswith(".pcd")  # PCD is written as float32 (io docs)
    np.testing.assert_allclose(back, points.astype(np.float64), rtol=1e-7 if float32_file else 1e-15)
    assert os.listdir(tmp_path) == [name]  # no temporary files left
    mask = os.umask(0)
    os.umask(mask)
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~mask  # an ordinary file, not mkstemp's private one


@pytest.mark.parametrize("name,kwargs", [("o.ply", {"write_ascii": True}), ("o.ply", {"write_ascii": False}),
                                         ("o.pcd", {"write_ascii": True}), ("o.pcd", {"write_ascii": False}),
                                         ("o.xyz", {})])
def test_reads_files_written_by_open3d(tmp_path, cloud, name, kwargs):
    o3d = pytest.importorskip("open3d", reason="cross-checking file formats needs open3d (the test extra)")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    pcd.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (len(cloud), 1)))  # extra fields to skip
    pcd.colors = o3d.utility.Vector3dVector(np.full((len(cloud), 3), 0.5))
    assert o3d.io.write_point_cloud(str(tmp_path / name), pcd, **kwargs)
    rtol = 1e-5 if name.endswith(".ply") and kwargs["write_ascii"] else 1e-7  # Open3D prints 6 digits there
    np.testing.assert_allclose(io.read(tmp_path / name), cloud, rtol=rtol)


@pytest.mark.parametrize("name", ["w.ply", "w.pcd", "w.xyz"])
def test_open3d_reads_our_files(tmp_path, cloud, name):
    o3d = pytest.importorskip("open3d", reason="cross-checking file formats needs open3d (the test extra)")
    io.write(tmp_path / name, cloud)
    np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(tmp_path / name)).points), cloud, rtol=1e-7)


def test_ply_with_faces_and_extra_properties(tmp_path):
    text = ("ply\nformat ascii 1.0\ncomment a mesh\nelement vertex 3\nproperty float nx\nproperty float x\n"
            "property float y\nproperty float z\nproperty uchar red\nelement face 1\n"
            "property list uchar int vertex_indices\nend_header\n"
            "9 1 2 3 255\n9 4 5 6 0\n9 7 8 9 1\n3 0 1 2\n")
    (tmp_path / "m.ply").write_text(text)
    np.testing.assert_array_equal(io.read(tmp_path / "m.ply"), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def test_big_endian_ply(tmp_path, cloud):
    header = "ply\nformat binary_big_endian 1.0\nelement vertex 257\nproperty double x\nproperty double y\n" \
             "property double z\nend_header\n"
    (tmp_path / "b.ply").write_bytes(header.encode() + cloud.astype(">f8").tobytes())
    np.testing.assert_array_equal(io.read(tmp_path / "b.ply"), cloud)


def test_text_with_comments_commas_and_extra_columns(tmp_path):
    (tmp_path / "p.txt").write_text("# x,y,z,r,g,b\n1,2,3,0,0,0\n\n4, 5, 6, 1, 1, 1  # last\n")
    np.testing.assert_array_equal(io.read(tmp_path / "p.txt"), [[1, 2, 3], [4, 5, 6]])


def test_text_headers_as_other_tools_write_them(tmp_path):
    """A first line of column names (CSV, CloudCompare's ``//X,Y,Z``) or a lone point count (.pts) is
    skipped; the same on a later line, or a first line of one or two numbers, is an error."""
    for name, text in [("names.csv", "x,y,z,intensity\n1,2,3,7\n4,5,6,8\n"),
                       ("cc.asc", "//X,Y,Z,R,G,B\n1 2 3 0 0 0\n4 5 6 0 0 0\n"),
                       ("scan.pts", "2\n1 2 3 -1500 10 20 30\n4 5 6 -1400 10 20 30\n")]:
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(io.read(tmp_path / name), [[1, 2, 3], [4, 5, 6]], err_msg=name)
    (tmp_path / "two_headers.csv").write_text("x,y,z\nX,Y,Z\n1,2,3\n")
    _bad(tmp_path / "two_headers.csv", "line 2 is not numbers")
    (tmp_path / "short.xyz").write_text("1.5 2\n1 2 3\n")
    _bad(tmp_path / "short.xyz", "not three coordinates", "line 1")
    io.write(tmp_path / "w.csv", np.eye(3))
    assert (tmp_path / "w.csv").read_text().splitlines()[:2] == ["x,y,z", "1,0,0"]
    io.write(tmp_path / "w.pts", np.eye(3))
    assert (tmp_path / "w.pts").read_text().splitlines()[0] == "3"


def test_max_points_reads_a_seeded_subset(tmp_path, cloud):
    for name in ("s.ply", "s.npy", "s.xyz", "s.pcd"):
        io.write(tmp_path / name, cloud)
        points, total = io.read(tmp_path / name, max_points=100, seed=3, return_count=True)
        assert total == len(cloud) and points.shape == (100, 3)
        rows = [np.flatnonzero(np.all(np.isclose(cloud, p, rtol=1e-7), axis=1)) for p in points]
        assert all(len(r) == 1 for r in rows)
        assert np.all(np.diff([r[0] for r in rows]) > 0)  # file order kept, no repeats
        np.testing.assert_array_equal(points, io.read(tmp_path / name, max_points=100, seed=3))


# ------------------------------------------------------------------------------------------- bad files


def _bad(path, *fragments):
    with pytest.raises(io.CloudFileError) as info:
        io.read(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path))
    for fragment in fragments:
        assert fragment in message, message


def test_missing_file_directory_and_unknown_format(tmp_path):
    _bad(tmp_path / "none.ply", "no such file")
    os.mkdir(tmp_path / "dir.ply")
    _bad(tmp_path / "dir.ply", "directory")
    (tmp_path / "c.obj").write_text("v 1 2 3\n")
    _bad(tmp_path / "c.obj", "unknown format", ".ply")
    (tmp_path / "noext").write_text("1 2 3\n")
    _bad(tmp_path / "noext", "unknown format")


def test_unreadable_file(tmp_path):
    (tmp_path / "garbage.npy").write_bytes(b"\x00\x01not a numpy file")
    _bad(tmp_path / "garbage.npy", "unreadable")
    (tmp_path / "latin1.xyz").write_bytes("1 2 3 \xe9\n".encode("latin-1"))
    _bad(tmp_path / "latin1.xyz", "unreadable")
    if os.geteuid() == 0:  # root reads any file whatever its mode
        return
    (tmp_path / "secret.xyz").write_text("1 2 3\n")
    os.chmod(tmp_path / "secret.xyz", 0)
    _bad(tmp_path / "secret.xyz", "permission denied")


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("name", ["n.ply", "n.pcd", "n.xyz", "n.npy"])
def test_nan_and_inf_are_refused(tmp_path, cloud, name, bad_value):
    points = cloud.copy()
    points[17, 1] = bad_value
    io.write(tmp_path / name, points)
    _bad(tmp_path / name, "NaN or Inf", "row 17")


def test_not_three_coordinates(tmp_path):
    np.save(tmp_path / "two.npy", np.zeros((10, 2)))
    _bad(tmp_path / "two.npy", "not three coordinates", "(10, 2)")
    np.save(tmp_path / "flat.npy", np.zeros(30))
    _bad(tmp_path / "flat.npy", "not three coordinates")
    (tmp_path / "two.xyz").write_text("1 2 3\n4 5\n")
    _bad(tmp_path / "two.xyz", "not three coordinates", "line 2")
    (tmp_path / "xy.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                     "property float y\nend_header\n1 2\n")
    _bad(tmp_path / "xy.ply", "not three coordinates", "no z")
    (tmp_path / "xy.pcd").write_text("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\n"
                                     "HEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n")
    _bad(tmp_path / "xy.pcd", "not three coordinates")


def test_malformed_and_truncated_files(tmp_path, cloud):
    (tmp_path / "junk.ply").write_bytes(os.urandom(300))
    _bad(tmp_path / "junk.ply", "not a PLY file")
    io.write(tmp_path / "cut.ply", cloud)
    data = (tmp_path / "cut.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-100])
    _bad(tmp_path / "cut.ply", "ends before its 257 vertices")
    io.write(tmp_path / "cut.pcd", cloud)
    (tmp_path / "cut.pcd").write_bytes((tmp_path / "cut.pcd").read_bytes()[:-100])
    _bad(tmp_path / "cut.pcd", "ends before its 257 points")
    (tmp_path / "words.xyz").write_text("1 2 3\nx y z\n")
    _bad(tmp_path / "words.xyz", "line 2 is not numbers")
    (tmp_path / "c.pcd").write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
                                    "POINTS 1\nDATA binary_compressed\n")
    _bad(tmp_path / "c.pcd", "binary_compressed", "re-save")
    (tmp_path / "noend.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\n")
    _bad(tmp_path / "noend.ply", "end_header")


def test_failed_write_leaves_nothing(tmp_path, cloud):
    with pytest.raises(ValueError):
        io.write(tmp_path / "bad.ply", cloud[:, :2])
    with pytest.raises(io.CloudFileError, match="does not exist"):
        io.write(tmp_path / "missing" / "a.ply", cloud)
    with pytest.raises(io.CloudFileError, match="unknown format"):
        io.write(tmp_path / "a.stl", cloud)
    assert os.listdir(tmp_path) == []
