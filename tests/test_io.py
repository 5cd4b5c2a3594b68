"""Point-cloud files: every format read back as written (ours and Open3D's), and every bad file refused."""

from __future__ import annotations

import os

import numpy as np
import pytest

from dit_jax import io
from dit_jax.io import text as io_text


@pytest.fixture
def cloud() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(257, 3)) * [3.0, 0.5, 100.0] + [1000.0, -2.0, 0.25]


@pytest.mark.parametrize(
    "name,binary",
    [
        ("a.ply", True),
        ("a.ply", False),
        ("a.pcd", True),
        ("a.pcd", False),
        ("a.xyz", False),
        ("a.txt", False),
        ("a.csv", False),
        ("a.asc", False),
        ("a.pts", False),
        ("a.npy", True),
    ],
)
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


@pytest.mark.parametrize(
    "name,kwargs",
    [
        ("o.ply", {"write_ascii": True}),
        ("o.ply", {"write_ascii": False}),
        ("o.pcd", {"write_ascii": True}),
        ("o.pcd", {"write_ascii": False}),
        ("o.xyz", {}),
    ],
)
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


def test_ply_extra_properties_and_elements_are_skipped(tmp_path):
    """Properties around x, y, z are skipped, and so are other elements; faces that list no vertices (an
    ``element face 0``, as MeshLab writes clouds, or a face element without ``vertex_indices``) leave a cloud."""
    for faces in (
        "element face 0\nproperty list uchar int vertex_indices\n",
        "element face 1\nproperty list uchar int other_list\n",
    ):
        text = (
            "ply\nformat ascii 1.0\ncomment a cloud\nelement vertex 3\nproperty float nx\nproperty float x\n"
            "property float y\nproperty float z\nproperty uchar red\n" + faces + "end_header\n"
            "9 1 2 3 255\n9 4 5 6 0\n9 7 8 9 1\n" + ("3 0 1 2\n" if "1" in faces.split()[2] else "")
        )
        (tmp_path / "m.ply").write_text(text)
        np.testing.assert_array_equal(io.read(tmp_path / "m.ply"), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
        b"element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    (tmp_path / "b.ply").write_bytes(header + np.eye(3, dtype="<f4").tobytes())  # an empty list element first
    np.testing.assert_array_equal(io.read(tmp_path / "b.ply"), np.eye(3))


def test_an_ascii_range_scan_reads_its_vertices_as_plyfile_does(tmp_path):
    """A range scan's ASCII PLY (float32 vertices, then a scan-grid element of lists, as the Stanford
    scanner writes) reads through NumPy's loader into what plyfile reads; a file with its vertices after
    another element, or a short row, still goes through plyfile and reads or fails as before."""
    from plyfile import PlyData

    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3)).astype(np.float32) * 0.1
    rows = "".join(f"{x:.7g} {y:.7g} {z:.7g} \n" for x, y, z in points)
    grid = "".join(f"1 {i}\n" if i % 3 else "0\n" for i in range(60))
    header = (
        "ply\nformat ascii 1.0\nobj_info num_cols 10\nelement vertex 50\nproperty float x\n"
        "property float y\nproperty float z\nelement range_grid 60\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    (tmp_path / "scan.ply").write_text(header + rows + grid)
    data = PlyData.read(str(tmp_path / "scan.ply"))["vertex"].data
    expected = np.stack([data[a] for a in "xyz"], axis=1).astype(np.float64)
    np.testing.assert_array_equal(io.read(tmp_path / "scan.ply"), expected)
    assert io.read(tmp_path / "scan.ply", max_points=20, return_count=True)[1] == 50
    first_grid = header.replace("element vertex 50\nproperty float x\nproperty float y\nproperty float z\n", "")
    first_grid = first_grid.replace(
        "end_header", "element vertex 50\nproperty float x\nproperty float y\nproperty float z\nend_header"
    )
    (tmp_path / "grid_first.ply").write_text(first_grid + grid + rows)
    np.testing.assert_array_equal(io.read(tmp_path / "grid_first.ply"), expected)
    (tmp_path / "short.ply").write_text(header + rows.replace(" \n", "\n", 1).split("\n", 1)[1] + grid)
    with pytest.raises(io.CloudFileError, match="malformed PLY"):
        io.read(tmp_path / "short.ply")


def test_big_endian_ply(tmp_path, cloud):
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 257\nproperty double x\nproperty double y\n"
        "property double z\nend_header\n"
    )
    (tmp_path / "b.ply").write_bytes(header.encode() + cloud.astype(">f8").tobytes())
    np.testing.assert_array_equal(io.read(tmp_path / "b.ply"), cloud)


def test_text_with_comments_commas_and_extra_columns(tmp_path):
    (tmp_path / "p.txt").write_text("# x,y,z,r,g,b\n1,2,3,0,0,0\n\n4, 5, 6, 1, 1, 1  # last\n")
    np.testing.assert_array_equal(io.read(tmp_path / "p.txt"), [[1, 2, 3], [4, 5, 6]])


def test_text_headers_as_other_tools_write_them(tmp_path):
    """A first line of column names (CSV, CloudCompare's ``//X,Y,Z``) or a lone point count (.pts) is
    skipped; the same on a later line, or a first line of one or two numbers, is an error."""
    for name, text in [
        ("names.csv", "x,y,z,intensity\n1,2,3,7\n4,5,6,8\n"),
        ("cc.asc", "//X,Y,Z,R,G,B\n1 2 3 0 0 0\n4 5 6 0 0 0\n"),
        ("scan.pts", "2\n1 2 3 -1500 10 20 30\n4 5 6 -1400 10 20 30\n"),
    ]:
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
    (tmp_path / "c.e57").write_text("v 1 2 3\n")
    _bad(tmp_path / "c.e57", "unknown format", ".ply", ".las", ".obj")
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


@pytest.mark.parametrize("name", ["n.ply", "n.pcd", "n.xyz", "n.npy"])
def test_nonfinite_points_are_left_out_on_request(tmp_path, cloud, name):
    points = cloud.copy()
    points[::3] = np.nan  # an organized cloud's pixels without a return
    points[1, 2] = np.inf
    io.write(tmp_path / name, points)
    finite = np.isfinite(points).all(axis=1)
    with pytest.warns(io.NonFiniteWarning, match=f"left out {(~finite).sum()} of 257 points"):
        back, total = io.read(tmp_path / name, drop_nonfinite=True, return_count=True)
    assert total == finite.sum()
    np.testing.assert_allclose(back, points[finite], rtol=1e-7)
    with pytest.warns(io.NonFiniteWarning):  # the subset is drawn among the finite points: all of them are
        sub, total = io.read(tmp_path / name, drop_nonfinite=True, return_count=True, max_points=100)
    assert sub.shape == (100, 3) and total == finite.sum() and np.isfinite(sub).all()
    assert (sub[:, None] == back[None]).all(axis=2).any(axis=1).all()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning where nothing is left out
        io.write(tmp_path / ("whole" + name[1:]), cloud)
        np.testing.assert_allclose(io.read(tmp_path / ("whole" + name[1:]), drop_nonfinite=True), cloud, rtol=1e-7)
    io.write(tmp_path / name, np.full((5, 3), np.nan))
    _bad(tmp_path / name, "NaN or Inf", "row 0", "drop_nonfinite")
    with pytest.raises(io.CloudFileError, match="all 5 points have NaN or Inf"):
        io.read(tmp_path / name, drop_nonfinite=True)


def test_compressed_pcd_as_open3d_writes_it(tmp_path, cloud):
    o3d = pytest.importorskip("open3d", reason="writing compressed PCD files needs open3d (the test extra)")
    points = np.concatenate([cloud, np.zeros((300, 3)), cloud[:50]])  # runs and repeats: back references
    o3d_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d_cloud.colors = o3d.utility.Vector3dVector(np.random.default_rng(2).uniform(size=points.shape))
    path = str(tmp_path / "c.pcd")
    assert o3d.io.write_point_cloud(path, o3d_cloud, write_ascii=False, compressed=True)
    assert b"DATA binary_compressed" in open(path, "rb").read(400)
    np.testing.assert_array_equal(io.read(path), points.astype(np.float32))
    np.testing.assert_array_equal(
        io.read(path, max_points=20, seed=3),
        io.read(path)[np.sort(np.random.default_rng(3).choice(len(points), 20, replace=False))],
    )


@pytest.mark.parametrize("version,point_format", [("1.2", 0), ("1.2", 3), ("1.4", 6), ("1.4", 8)])
def test_las_files_as_laspy_writes_them(tmp_path, cloud, version, point_format):
    laspy = pytest.importorskip("laspy", reason="writing LAS files needs laspy (the test extra)")
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales, header.offsets = [0.001, 0.001, 0.0001], [1000.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.T
    las.write(str(tmp_path / "a.las"))
    back = laspy.read(str(tmp_path / "a.las"))
    expected = np.stack([back.x, back.y, back.z], axis=1)
    np.testing.assert_array_equal(io.read(tmp_path / "a.las"), expected)
    np.testing.assert_allclose(expected, cloud, atol=5e-4)  # the scale's rounding
    rows = np.sort(np.random.default_rng(4).choice(len(cloud), 50, replace=False))
    np.testing.assert_array_equal(io.read(tmp_path / "a.las", max_points=50, seed=4), expected[rows])
    las.write(str(tmp_path / "a.laz"))  # compressed: laspy's LAZ backend (lazrs) reads it back
    np.testing.assert_array_equal(io.read(tmp_path / "a.laz"), expected)
    data = bytearray((tmp_path / "a.las").read_bytes())
    (tmp_path / "c.las").write_bytes(bytes(data[:-40]))
    _bad(tmp_path / "c.las", f"ends before its {len(cloud)} points")
    (tmp_path / "d.las").write_bytes(b"LASX" + bytes(data[4:]))
    _bad(tmp_path / "d.las", "Invalid file signature")
    with pytest.raises(io.CloudFileError, match="unknown format '.las'"):
        io.write(tmp_path / "e.las", cloud)  # read only


@pytest.mark.parametrize(
    "kwargs", [{"write_ascii": True}, {"write_ascii": False}, {"write_ascii": False, "compressed": True}]
)
def test_a_moved_pcd_keeps_its_fields_and_moves_its_viewpoint(tmp_path, cloud, kwargs):
    o3d = pytest.importorskip("open3d", reason="cross-checking PCD files needs open3d (the test extra)")
    from dit_jax.data.pairs import euler_zyx_to_matrix
    from dit_jax.data.scans import quaternion_matrix

    rng = np.random.default_rng(1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    pcd.normals = o3d.utility.Vector3dVector(rng.normal(size=cloud.shape))
    pcd.normalize_normals()
    pcd.colors = o3d.utility.Vector3dVector(rng.random(cloud.shape))
    assert o3d.io.write_point_cloud(str(tmp_path / "a.pcd"), pcd, **kwargs)
    data = (tmp_path / "a.pcd").read_bytes()
    q = np.array([0.1, -0.3, 0.2, 0.9]) / np.linalg.norm([0.1, -0.3, 0.2, 0.9])  # (x, y, z, w)
    viewpoint = f"VIEWPOINT 1 2 3 {q[3]} {q[0]} {q[1]} {q[2]}".encode()
    (tmp_path / "a.pcd").write_bytes(data.replace(b"VIEWPOINT 0 0 0 1 0 0 0", viewpoint))
    original = o3d.io.read_point_cloud(str(tmp_path / "a.pcd"))
    rotation, translation = euler_zyx_to_matrix([30.0, -20.0, 10.0]), np.array([5.0, -1.0, 0.25])
    io.move_file(tmp_path / "a.pcd", tmp_path / "m.pcd", rotation, translation)
    moved = o3d.io.read_point_cloud(str(tmp_path / "m.pcd"))
    np.testing.assert_allclose(
        np.asarray(moved.points), np.asarray(original.points) @ rotation.T + translation, atol=1e-4
    )  # float32 fields
    np.testing.assert_allclose(np.asarray(moved.normals), np.asarray(original.normals) @ rotation.T, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(moved.colors), np.asarray(original.colors))
    header = (tmp_path / "m.pcd").read_bytes().split(b"\nDATA ")[0].decode().splitlines()
    # ASCII stays ASCII; binary_compressed comes back binary, which PCL and Open3D read alike
    assert (b"\nDATA ascii\n" if kwargs["write_ascii"] else b"\nDATA binary\n") in (tmp_path / "m.pcd").read_bytes()
    (view,) = [np.array(line.split()[1:], float) for line in header if line.startswith("VIEWPOINT")]
    np.testing.assert_allclose(view[:3], rotation @ [1, 2, 3] + translation, atol=1e-12)
    np.testing.assert_allclose(quaternion_matrix([*view[4:], view[3]]), rotation @ quaternion_matrix(q), atol=1e-12)
    keys = ("FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "POINTS")
    layout = lambda lines: {line.split()[0]: line.split()[1:] for line in lines if line.startswith(keys)}  # noqa: E731
    assert layout(header) == layout((tmp_path / "a.pcd").read_bytes().split(b"\nDATA ")[0].decode().splitlines())


def test_files_that_cannot_be_moved_are_refused_and_nothing_is_written(tmp_path):
    head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty {0} x\nproperty {0} y\nproperty {0} z\nend_header\n"
    bad = {
        "short_row.ply": (head.format("float") + "1 2 3\n4 5\n", "row 1: property 'z': early end-of-line"),
        "integers.ply": (head.format("int") + "1 2 3\n4 5 6\n", "stored as integers would be rounded"),
        "flat.pcd": (
            "VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n",
            "no z field",
        ),
        "word.ply": (head.format("float") + "1 2 3\n4 5 a\n", "malformed input"),
    }
    for name, (text, fragment) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(io.CloudFileError, match=fragment):
            io.move_file(tmp_path / name, tmp_path / f"out{os.path.splitext(name)[1]}", np.eye(3), np.zeros(3))
    with pytest.raises(io.CloudFileError, match="no such file"):
        io.move_file(tmp_path / "missing.las", tmp_path / "out.las", np.eye(3), np.zeros(3))
    with pytest.raises(io.CloudFileError, match="written as .ply"):
        io.move_file(tmp_path / "word.ply", tmp_path / "out.pcd", np.eye(3), np.zeros(3))
    with pytest.raises(io.CloudFileError, match="unknown format to move '.xyz'"):
        io.move_file(tmp_path / "a.xyz", tmp_path / "out.xyz", np.eye(3), np.zeros(3))
    assert sorted(os.listdir(tmp_path)) == sorted(bad)


def test_a_moved_las_keeps_every_attribute_at_its_scale(tmp_path, cloud):
    laspy = pytest.importorskip("laspy", reason="writing LAS files needs laspy (the test extra)")
    from dit_jax.data.pairs import euler_zyx_to_matrix

    las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    las.header.scales, las.header.offsets = [0.001] * 3, [1000.0, -2.0, 0.0]
    las.x, las.y, las.z = cloud.T
    las.intensity, las.classification = np.arange(len(cloud)), np.arange(len(cloud)) % 7
    las.write(str(tmp_path / "a.las"))
    rotation = euler_zyx_to_matrix([30.0, -20.0, 10.0])
    for translation in ([5.0, -1.0, 0.25], [3e6, 0.0, 0.0]):  # the second overflows the offset's integers
        io.move_file(tmp_path / "a.las", tmp_path / "m.las", rotation, translation)
        before, after = laspy.read(str(tmp_path / "a.las")), laspy.read(str(tmp_path / "m.las"))
        points = np.stack([after.x, after.y, after.z], axis=1)
        expected = np.stack([before.x, before.y, before.z], axis=1) @ rotation.T + translation
        np.testing.assert_allclose(points, expected, atol=0.0005 + 1e-9)  # rounded to the file's 1 mm
        np.testing.assert_array_equal(after.intensity, before.intensity)
        np.testing.assert_array_equal(after.classification, before.classification)
        np.testing.assert_allclose(after.header.mins, points.min(axis=0), atol=1e-9)
        np.testing.assert_allclose(after.header.maxs, points.max(axis=0), atol=1e-9)
        np.testing.assert_array_equal(io.read(tmp_path / "m.las"), points)
    assert after.header.offsets[0] != 1000.0  # re-centred
    (tmp_path / "short.las").write_bytes((tmp_path / "a.las").read_bytes()[:-40])
    with pytest.raises(io.CloudFileError, match=f"ends before its {len(cloud)} points"):
        io.move_file(tmp_path / "short.las", tmp_path / "short_moved.las", rotation, translation)
    assert not (tmp_path / "short_moved.las").exists() and not list(tmp_path.glob(".tmp-*"))


def _box_mesh_files(tmp_path):
    """A 2 x 1 x 0.5 box (area 7) as OBJ (quads, one face by negative indices), OFF (ModelNet's header) and
    ASCII and binary STL."""
    corners = np.array([[x, y, z] for x in (0, 2) for y in (0, 1) for z in (0, 0.5)], float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    obj = "# a box\no box\n" + "".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in corners) + "vt 0 0\nvn 0 0 1\n"
    obj += "".join(f"f {' '.join(f'{i + 1}/1/1' for i in quad)}\n" for quad in quads[:-1])
    obj += f"f {' '.join(str(i - 8) for i in quads[-1])}\n"
    (tmp_path / "box.obj").write_text(obj)
    off = f"OFF{len(corners)} {len(quads)} 0\n" + "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in corners)
    off += "".join(f"4 {' '.join(map(str, quad))} 255 0 0\n" for quad in quads)  # with a colour
    (tmp_path / "box.off").write_text(off)
    triangles = np.array([[q[0], q[i], q[i + 1]] for q in quads for i in (1, 2)])
    stl = "solid box\n" + "".join(
        "facet normal 0 0 0\nouter loop\n"
        + "".join(f"vertex {x:g} {y:g} {z:g}\n" for x, y, z in corners[t])
        + "endloop\nendfacet\n"
        for t in triangles
    )
    (tmp_path / "box_ascii.stl").write_text(stl + "endsolid box\n")
    record = np.zeros(len(triangles), [("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
    record["corners"] = corners[triangles]
    (tmp_path / "box.stl").write_bytes(
        b"solid: binary files may start so too".ljust(80) + np.uint32(len(triangles)).tobytes() + record.tobytes()
    )
    # PLY: the first quad as two triangles (lists of two lengths), normals, colours, a flag before the list
    faces = [quads[0][:3], [quads[0][0], quads[0][2], quads[0][3]]] + quads[1:]
    header = (
        "ply\nformat {} 1.0\nelement vertex 8\nproperty {} x\nproperty {} y\nproperty {} z\n"
        "property float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n"
        f"element face {len(faces)}\nproperty uchar flags\nproperty list uchar int vertex_indices\n"
        "element note 1\nproperty int mark\nend_header\n"
    )
    rows = "".join(f"{x:g} {y:g} {z:g} 0 0 1 {i}\n" for i, (x, y, z) in enumerate(corners))
    rows += "".join(f"7 {len(f)} {' '.join(map(str, f))}\n" for f in faces) + "42\n"
    (tmp_path / "box_ascii.ply").write_text(header.format("ascii", *["double"] * 3) + rows)
    vertex = np.zeros(8, [("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("n", ">f4", 3), ("red", "u1")])
    vertex["x"], vertex["y"], vertex["z"], vertex["n"], vertex["red"] = *corners.T, [0, 0, 1], np.arange(8)
    data = (
        vertex.tobytes()
        + b"".join(np.array([7, len(f)], "u1").tobytes() + np.array(f, ">i4").tobytes() for f in faces)
        + np.array([42], ">i4").tobytes()
    )
    (tmp_path / "box.ply").write_bytes(header.format("binary_big_endian", *["float"] * 3).encode() + data)
    return corners, ["box.obj", "box.off", "box_ascii.stl", "box.stl", "box_ascii.ply", "box.ply"]


def test_meshes_are_sampled_uniformly_over_their_surface(tmp_path):
    corners, names = _box_mesh_files(tmp_path)
    for name in names:
        vertices, triangles = io.read_mesh(tmp_path / name)
        assert triangles.shape == (12, 3), name
        a, b, c = (vertices[triangles[:, i]] for i in range(3))
        assert np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2 == pytest.approx(7.0), name
        points, count = io.read(tmp_path / name, mesh_points=14_000, seed=1, return_count=True)
        assert points.shape == (14_000, 3) and count == 14_000
        on_face = np.isclose(points, 0).any(axis=1) | np.isclose(points, [2, 1, 0.5]).any(axis=1)
        assert on_face.all() and (points >= 0).all() and (points <= [2, 1, 0.5]).all()
        top = np.isclose(points[:, 2], 0.5).mean()  # a face of area 2 of the 7
        assert top == pytest.approx(2 / 7, abs=0.015), name
        np.testing.assert_array_equal(points, io.read(tmp_path / name, mesh_points=14_000, seed=1))
        assert io.read(tmp_path / name, max_points=500).shape == (500, 3)  # max_points caps the samples
    assert not np.array_equal(io.read(tmp_path / names[0], seed=1), io.read(tmp_path / names[0], seed=2))


def test_a_moved_mesh_keeps_all_but_its_coordinates(tmp_path):
    from dit_jax.data.pairs import euler_zyx_to_matrix

    _, names = _box_mesh_files(tmp_path)
    rotation, translation = euler_zyx_to_matrix([30.0, -20.0, 10.0]), np.array([5.0, -1.0, 0.25])
    for name in names:
        moved = tmp_path / f"moved_{name}"
        io.move_file(tmp_path / name, moved, rotation, translation)
        vertices, triangles = io.read_mesh(tmp_path / name)
        moved_vertices, moved_triangles = io.read_mesh(moved)
        np.testing.assert_array_equal(moved_triangles, triangles)
        exact = name.endswith(("obj", "off", "ascii.stl", "ascii.ply"))  # text keeps float64; binaries: float32
        np.testing.assert_allclose(moved_vertices, vertices @ rotation.T + translation, atol=1e-12 if exact else 1e-5)
    text = (tmp_path / "moved_box.obj").read_text().splitlines()
    original = (tmp_path / "box.obj").read_text().splitlines()
    assert [line for line in text if not line.startswith(("v ", "vn "))] == [
        line for line in original if not line.startswith(("v ", "vn "))
    ]  # faces, groups, texture coordinates
    (normal,) = [np.array(line.split()[1:], float) for line in text if line.startswith("vn ")]
    np.testing.assert_allclose(normal, rotation @ [0, 0, 1], atol=1e-12)  # turned, not moved
    assert all(line.endswith(" 255 0 0") for line in (tmp_path / "moved_box.off").read_text().splitlines()[-6:])
    assert (tmp_path / "moved_box.stl").read_bytes()[:84] == (tmp_path / "box.stl").read_bytes()[:84]
    for name in ("box.ply", "box_ascii.ply"):  # PLY: normals turned; colours, flags, faces and the rest kept
        before, after = (tmp_path / name).read_bytes(), (tmp_path / f"moved_{name}").read_bytes()
        assert len(after) == len(before) if name == "box.ply" else after.endswith(before[before.rindex(b" 7\n") :])
        if name == "box.ply":
            start = before.index(b"end_header\n") + 11
            table = np.frombuffer(after[start : start + 8 * 25], [("xyz", ">f4", 3), ("n", ">f4", 3), ("red", "u1")])
            np.testing.assert_allclose(table["n"], np.tile(rotation @ [0, 0, 1], (8, 1)), atol=1e-6)
            assert table["red"].tolist() == list(range(8)) and after[start + 200 :] == before[start + 200 :]
    lines = (tmp_path / "moved_box_ascii.ply").read_text().splitlines()
    np.testing.assert_allclose(np.array(lines[16].split()[3:6], float), rotation @ [0, 0, 1], atol=1e-6)
    assert lines[16].split()[6] == "0" and lines[:16] == (tmp_path / "box_ascii.ply").read_text().splitlines()[:16]
    with pytest.raises(io.CloudFileError, match="written as .obj"):
        io.move_file(tmp_path / "box.obj", tmp_path / "x.stl", rotation, translation)
    (tmp_path / "bad.obj").write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(io.CloudFileError, match="not defined"):
        io.move_file(tmp_path / "bad.obj", tmp_path / "x.obj", rotation, translation)
    assert not (tmp_path / "x.obj").exists() and not list(tmp_path.glob(".tmp-*"))


def test_text_meshes_with_comments_colours_and_odd_spacing_read_and_move(tmp_path):
    """The text mesh readers split all lines at once: comments, blank lines, tabs, non-ASCII spaces, colours,
    mixed polygons and negative indices must still land where a line-by-line reading puts them."""
    from dit_jax.data.pairs import euler_zyx_to_matrix

    square = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0.5, 0.5, 1)]
    expected = [[0, 1, 2], [0, 2, 3], [0, 1, 4], [1, 2, 4]]
    (tmp_path / "odd.obj").write_text(
        "# top\nv 0 0 0\nv\t1 0 0 # a comment\nv 1  1 0 1.0\nvn 0 0 1\nv 0\u00a01 0\nf 1/1/1 2/2/2 3/3/3 4/4/4\n"
        "\nv 0.5 0.5 1\nf -5 -4 -1\nf 2//1 3//1 5//1\nl 1 2\n"
    )
    (tmp_path / "odd.off").write_text(
        "COFF\n# counts next\n5 3 0\n0 0 0 9 9 9 1\n\n1 0 0 9 9 9 1 # x\n1 1 0 9 9 9 1\n0\u00a01 0 9 9 9 1\n"
        "0.5 0.5 1 9 9 9 1\n4 0 1 2 3 255 0 0\n3\t0 1 4\n3 1 2 4 # last\n"
    )
    rotation, translation = euler_zyx_to_matrix([40.0, 10.0, -25.0]), np.array([0.5, -2.0, 3.0])
    for name in ("odd.obj", "odd.off"):
        vertices, triangles = io.read_mesh(tmp_path / name)
        np.testing.assert_array_equal(vertices, square)
        assert triangles.tolist() == expected
        io.move_file(tmp_path / name, tmp_path / f"moved_{name}", rotation, translation)
        moved_vertices, moved_triangles = io.read_mesh(tmp_path / f"moved_{name}")
        np.testing.assert_allclose(moved_vertices, np.array(square) @ rotation.T + translation, atol=1e-12)
        assert moved_triangles.tolist() == expected
    obj = (tmp_path / "moved_odd.obj").read_text().splitlines()
    assert obj[2].endswith(" # a comment") and obj[3].endswith(" 1.0") and obj[0] == "# top"
    np.testing.assert_allclose(np.array(obj[4].split()[1:], float), rotation @ [0, 0, 1], atol=1e-12)
    off = (tmp_path / "moved_odd.off").read_text().splitlines()
    assert off[5].endswith(" 9 9 9 1 # x") and off[-3:] == ["4 0 1 2 3 255 0 0", "3\t0 1 4", "3 1 2 4 # last"]
    (tmp_path / "flat_normal.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 1\nf 1 2 3\n")
    with pytest.raises(io.CloudFileError, match="fewer than three coordinates"):
        io.move_file(tmp_path / "flat_normal.obj", tmp_path / "x.obj", rotation, translation)
    assert not (tmp_path / "x.obj").exists()


@pytest.mark.parametrize("end", ["\n", "\r\n"])
def test_ascii_stl_and_obj_read_and_move_whatever_their_indentation_case_and_line_ends(tmp_path, end):
    """CAD tools indent ASCII STL, some write it in capitals, Windows ends lines with CRLF: the corners are read
    all the same, and a moved file keeps every other line and every line end as it was."""
    from dit_jax.data.pairs import euler_zyx_to_matrix

    triangles = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 1], [2, 0, 1], [0, 3, 1]]], float)
    stl = [
        "solid part",
        "  facet normal 0 0 1",
        "    outer loop",
        "      vertex 0 0 0",
        "\tvertex 1 0 0",
        "      vertex 0 1 0",
        "    endloop",
        "  endfacet",
        "FACET NORMAL 0 0 1",
        "OUTER LOOP",
        "VERTEX 0 0 1",
        "VERTEX 2.0e0 0 1",
        "VERTEX 0 3 1",
        "ENDLOOP",
        "ENDFACET",
        "endsolid part",
    ]
    obj = ["# part", "v 0 0 0", "v 1 0 0", "v 0 1 0", "vn 0 0 1", "f 1 2 3"]
    rotation, translation = euler_zyx_to_matrix([30.0, -20.0, 10.0]), np.array([1.0, 2.0, 3.0])
    for name, lines, unchanged in (("part.stl", stl, [0, 2, 6, 7, 9, 13, 14, 15]), ("part.obj", obj, [0, 5])):
        (tmp_path / name).write_bytes(end.join(lines + [""]).encode())
        vertices, faces = io.read_mesh(tmp_path / name)
        expected = triangles if name.endswith("stl") else triangles[:1]
        np.testing.assert_array_equal(vertices[faces], expected)
        io.move_file(tmp_path / name, tmp_path / f"moved_{name}", rotation, translation)
        vertices, faces = io.read_mesh(tmp_path / f"moved_{name}")
        np.testing.assert_allclose(vertices[faces], expected @ rotation.T + translation, atol=1e-12)
        moved = (tmp_path / f"moved_{name}").read_bytes().decode()
        assert moved.count(end) == len(lines) and moved.endswith(end) and moved.count("\n") == len(lines)
        assert [moved.split(end)[i] for i in unchanged] == [lines[i] for i in unchanged]
    normal = (tmp_path / "moved_part.stl").read_bytes().decode().split(end)[8].split()
    assert normal[:2] == ["FACET", "NORMAL"]
    np.testing.assert_allclose(np.array(normal[2:], float), rotation @ [0, 0, 1], atol=1e-12)
    (tmp_path / "short.stl").write_text(
        "solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0\nvertex 1 0 0\n"
        "vertex 0 1 0\nendloop\nendfacet\nendsolid s\n"
    )
    _bad(tmp_path / "short.stl", "an STL vertex has fewer than three coordinates")


def test_an_ascii_stl_with_old_mac_line_ends_is_moved(tmp_path):
    """Lines ended by a lone "\r" are lines too, for reading and for moving alike."""
    stl = (
        "solid s\rfacet normal 0 0 1\r outer loop\r  vertex 0 0 0\r  vertex 1 0 0\r  vertex 0 1 0\r endloop\r"
        "endfacet\rendsolid s\r"
    )
    (tmp_path / "cr.stl").write_bytes(stl.encode())
    rotation, translation = np.eye(3)[[1, 2, 0]], np.array([1.0, 2.0, 3.0])
    io.move_file(tmp_path / "cr.stl", tmp_path / "moved.stl", rotation, translation)
    vertices, faces = io.read_mesh(tmp_path / "moved.stl")
    np.testing.assert_array_equal(
        vertices[faces][0], np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) @ rotation.T + translation
    )
    assert (tmp_path / "moved.stl").read_bytes().count(b"\r") == stl.count("\r")


@pytest.mark.parametrize("end", ["\n", "\r\n"])
def test_a_moved_ascii_ply_finds_its_vertices_after_other_elements(tmp_path, end):
    """Reading and moving an ASCII PLY locate its vertex rows alike: after the header and one line per item
    of every element before them, whatever the line ends."""
    text = (
        "ply|format ascii 1.0|element camera 2|property float f|element vertex 3|property double x|"
        "property double y|property double z|end_header|5|6|1 0 0|0 2 0|0 0 3|"
    ).replace("|", end)
    (tmp_path / "a.ply").write_bytes(text.encode())
    points = io.read(tmp_path / "a.ply")
    np.testing.assert_array_equal(points, np.diag([1.0, 2.0, 3.0]))
    io.move_file(tmp_path / "a.ply", tmp_path / "m.ply", np.eye(3)[[1, 2, 0]], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(io.read(tmp_path / "m.ply"), points[:, [1, 2, 0]] + [1.0, 2.0, 3.0])
    after = (tmp_path / "m.ply").read_bytes().decode()
    assert after.startswith(text[: text.index("1 0 0")]) and after.endswith(end) and after.count(end) == 14


def test_meshes_written_by_open3d(tmp_path):
    o3d = pytest.importorskip("open3d", reason="cross-checking mesh formats needs open3d (the test extra)")
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=12)
    mesh.compute_triangle_normals()  # STL needs them
    for name in ("s.obj", "s.off", "s.stl", "s.ply", "s_ascii.ply"):
        assert o3d.io.write_triangle_mesh(str(tmp_path / name), mesh, write_ascii="ascii" in name)
        vertices, triangles = io.read_mesh(tmp_path / name)
        back = o3d.io.read_triangle_mesh(str(tmp_path / name))
        np.testing.assert_allclose(
            vertices[triangles], np.asarray(back.vertices)[np.asarray(back.triangles)], atol=1e-6
        )
        io.move_file(tmp_path / name, tmp_path / f"moved_{name}", np.eye(3)[[1, 2, 0]], [1.0, 2.0, 3.0])
        moved = o3d.io.read_triangle_mesh(str(tmp_path / f"moved_{name}"))  # Open3D still reads it
        np.testing.assert_allclose(
            np.asarray(moved.vertices)[np.asarray(moved.triangles)],
            vertices[triangles][..., [1, 2, 0]] + [1.0, 2.0, 3.0],
            atol=1e-5,
        )


_PLY_TRIANGLE = (
    "ply\nformat {} 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
)


def test_an_obj_of_vertices_alone_is_a_cloud_and_bad_meshes_are_refused(tmp_path, cloud):
    (tmp_path / "cloud.obj").write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in cloud.tolist()))
    np.testing.assert_array_equal(io.read(tmp_path / "cloud.obj"), cloud)
    assert io.read(tmp_path / "cloud.obj", max_points=10).shape == (10, 3)
    bad_meshes = {
        "later.obj": ("v 0 0 0\nf 1 2 3\nv 1 0 0\nv 0 1 0\n", "a face names a vertex not defined before it"),
        "zero.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "not defined"),
        "flat.obj": ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "no area"),
        "short.off": ("OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "ends before its 4 vertices and 2 faces"),
        "far.off": ("OFF 3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "a face names a vertex the file does not have"),
        "four.off": ("4OFF\n", "OFF variant '4OFF' is not supported"),
        "two.off": ("OFF 3 1 0\n0 0 0\n1 0 0\n0 1\n3 0 1 2\n", "an OFF vertex has fewer than three coordinates"),
        "few.off": ("OFF 3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1\n", "fewer corners than its count"),
        "two.obj": ("v 0 0 0\nv 1 0 0\n# note\nv 0 1\n", "line 4: a vertex needs three coordinates"),
        "empty.stl": ("solid empty\nendsolid empty\n", "no vertices"),
        "short.ply": (_PLY_TRIANGLE.format("ascii") + "0 0 0\n1 0 0\n0 1 0\n3 0 1\n", "early end-of-line"),
        "far.ply": (_PLY_TRIANGLE.format("ascii") + "0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", "a face names a vertex"),
    }
    for name, (text, fragment) in bad_meshes.items():
        (tmp_path / name).write_text(text)
        _bad(tmp_path / name, fragment)
    (tmp_path / "junk.stl").write_bytes(os.urandom(200))
    _bad(tmp_path / "junk.stl", "not an STL file")
    triangle = np.eye(3, dtype="<f4").tobytes() + np.array([3], "u1").tobytes() + np.arange(3, dtype="<i4").tobytes()
    for cut in (1, 13):  # within the list, and before its length
        (tmp_path / "cut.ply").write_bytes(_PLY_TRIANGLE.format("binary_little_endian").encode() + triangle[:-cut])
        _bad(tmp_path / "cut.ply", "early end-of-file")
    (tmp_path / "whole.ply").write_bytes(_PLY_TRIANGLE.format("binary_little_endian").encode() + triangle)
    assert io.read_mesh(tmp_path / "whole.ply")[1].tolist() == [[0, 1, 2]]
    with pytest.raises(io.CloudFileError, match="unknown format '.obj'"):
        io.write(tmp_path / "out.obj", cloud)  # meshes are read, not written


def test_text_files_read_alike_by_both_readers(tmp_path):
    """NumPy's parser reads regular files; the line-by-line reader the rest. Both give the same points."""
    files = {
        "a.xyz": "1 2 3\n4\t5 6 7\n\n",  # tabs, a fourth column, a blank line
        "b.csv": "x,y,z\n1, 2, 3\n4,5,6\n",
        "c.txt": "# from CloudCompare\n\n//X,Y,Z\n1;2;3;9\n4;5;6;9 # a comment\n",
        "d.csv": "1,2,3,\n4,5,6,\n",  # a trailing separator is no header
        "e.xyz": "1,2,3\n4 5 6\n",  # separators mixed: line by line only
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(io.read(tmp_path / name), [[1, 2, 3], [4, 5, 6]], err_msg=name)
        by_line = io_text._read_text_by_line(str(tmp_path / name))
        np.testing.assert_array_equal(by_line, [[1, 2, 3], [4, 5, 6]], err_msg=name)
        fast = io_text._read_text_fast(str(tmp_path / name))
        assert (fast is None) == (name == "e.xyz") and (fast is None or np.array_equal(fast, by_line)), name
    (tmp_path / "empty.xyz").write_text("# nothing\n")
    assert io.read(tmp_path / "empty.xyz", drop_nonfinite=True).shape == (0, 3)


def test_not_three_coordinates(tmp_path):
    np.save(tmp_path / "two.npy", np.zeros((10, 2)))
    _bad(tmp_path / "two.npy", "not three coordinates", "(10, 2)")
    np.save(tmp_path / "flat.npy", np.zeros(30))
    _bad(tmp_path / "flat.npy", "not three coordinates")
    (tmp_path / "two.xyz").write_text("1 2 3\n4 5\n")
    _bad(tmp_path / "two.xyz", "not three coordinates", "line 2")
    (tmp_path / "xy.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n"
    )
    _bad(tmp_path / "xy.ply", "not three coordinates", "no z")
    (tmp_path / "xy.pcd").write_text(
        "VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n"
    )
    _bad(tmp_path / "xy.pcd", "not three coordinates")


def test_malformed_and_truncated_files(tmp_path, cloud):
    (tmp_path / "junk.ply").write_bytes(os.urandom(300))
    _bad(tmp_path / "junk.ply", "not a PLY file")
    io.write(tmp_path / "cut.ply", cloud)
    data = (tmp_path / "cut.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-100])
    _bad(tmp_path / "cut.ply", "row 252: early end-of-file")
    io.write(tmp_path / "cut.pcd", cloud)
    (tmp_path / "cut.pcd").write_bytes((tmp_path / "cut.pcd").read_bytes()[:-100])
    _bad(tmp_path / "cut.pcd", "malformed PCD file")
    (tmp_path / "words.xyz").write_text("1 2 3\nx y z\n")
    _bad(tmp_path / "words.xyz", "line 2 is not numbers")
    header = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n"
    (tmp_path / "c.pcd").write_bytes(header)
    _bad(tmp_path / "c.pcd", "malformed PCD file")  # no compressed data at all
    for broken in (
        np.array([13, 12], "<u4").tobytes() + b"\x0f" + bytes(12),  # a literal run past the data
        np.array([2, 12], "<u4").tobytes() + b"\x20\x05",  # a reference before the start
        np.array([13, 16], "<u4").tobytes() + b"\x0b" + bytes(12),
    ):  # 16 bytes, not 1 point of 12
        (tmp_path / "c.pcd").write_bytes(header + broken)
        _bad(tmp_path / "c.pcd", "malformed PCD file")
    (tmp_path / "noend.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\n")
    _bad(tmp_path / "noend.ply", "line 4: early end-of-file")  # the header never ends


def test_failed_write_leaves_nothing(tmp_path, cloud):
    with pytest.raises(ValueError):
        io.write(tmp_path / "bad.ply", cloud[:, :2])
    with pytest.raises(io.CloudFileError, match="does not exist"):
        io.write(tmp_path / "missing" / "a.ply", cloud)
    with pytest.raises(io.CloudFileError, match="unknown format"):
        io.write(tmp_path / "a.stl", cloud)
    assert os.listdir(tmp_path) == []


def test_a_pcd_whose_header_lies_about_its_count_and_a_pipe_are_refused(tmp_path, cloud):
    """A PCD's POINTS (and WIDTH x HEIGHT) must match the records it holds, as a PLY's count must; a named pipe
    (or any file that is not a regular file) is refused before reading, where reading would block."""
    io.write(tmp_path / "a.pcd", cloud, binary=False)
    text = (tmp_path / "a.pcd").read_text()
    (tmp_path / "more.pcd").write_text(text.replace("POINTS 257", "POINTS 1000").replace("WIDTH 257", "WIDTH 1000"))
    _bad(tmp_path / "more.pcd", "its header says POINTS 1,000")
    (tmp_path / "shape.pcd").write_text(text.replace("HEIGHT 1", "HEIGHT 2"))
    _bad(tmp_path / "shape.pcd", "HEIGHT 2")
    os.mkfifo(tmp_path / "pipe.ply")
    _bad(tmp_path / "pipe.ply", "not a regular file")
