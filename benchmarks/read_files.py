"""Seconds to read a cloud of every format ``dit_jax.io`` reads, and a mesh of every mesh format, beside Open3D,
and to write each file moved (``io.move_file``, what ``dit-register --out`` does with SRC's own format).

    python benchmarks/read_files.py [--points 1000000] [--sphere-resolution 300] [--repeats 3]

The cloud is random normal points (float64 where the format keeps it; PCD is float32), read with
``drop_nonfinite=True``; compressed PCD (those points, and an organized 1280 x 960 depth-camera cloud with NaN
pixels) and the meshes are written by Open3D (a UV sphere: 300 gives 179,402 vertices and 358,800 triangles;
ASCII STL, which Open3D cannot write, by this script), the LAS file by laspy (where installed). Prints a
markdown table of the best of ``--repeats`` runs; the mesh rows' reads include sampling ``io.MESH_POINTS``
surface points.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings

import numpy as np

from dit_jax import io


def best_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def write_ascii_stl(path: str, corners: np.ndarray, normals: np.ndarray) -> None:
    """An ASCII STL file of triangles ``corners`` (F, 3, 3) with ``normals`` (F, 3), indented as CAD tools do."""
    facet = (
        "  facet normal {:e} {:e} {:e}\n    outer loop\n"
        + "      vertex {:e} {:e} {:e}\n" * 3
        + "    endloop\n  endfacet\n"
    )
    values = np.concatenate([normals, corners.reshape(-1, 9)], axis=1).tolist()
    with open(path, "w") as f:
        f.write("solid mesh\n" + "".join(facet.format(*row) for row in values) + "endsolid mesh\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--sphere-resolution", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    import open3d as o3d

    warnings.simplefilter("ignore", io.NonFiniteWarning)  # the organized cloud's NaN pixels, left out

    cloud = np.random.default_rng(0).normal(size=(args.points, 3))
    rotation, translation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([1.0, 2.0, 3.0])

    def moved(path: str) -> float:
        stem, ext = os.path.splitext(path)
        if ext not in io.MOVE_FORMATS:
            return float("nan")
        return best_seconds(lambda: io.move_file(path, f"{stem}_moved{ext}", rotation, translation), args.repeats)

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        files = []
        for name, binary in (
            ("cloud.ply", True),
            ("cloud_ascii.ply", False),
            ("cloud.pcd", True),
            ("cloud_ascii.pcd", False),
            ("cloud.xyz", False),
            ("cloud.csv", False),
            ("cloud.npy", True),
        ):
            io.write(os.path.join(folder, name), cloud, binary=binary)
            files.append((name, "ours"))
        o3d_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
        o3d.io.write_point_cloud(os.path.join(folder, "cloud_compressed.pcd"), o3d_cloud, compressed=True)
        files.append(("cloud_compressed.pcd", "Open3D"))
        # A depth camera's organized cloud (smooth, a third of its pixels without a return): LZF finds
        # many short repeats in it, where random floats are mostly literal runs.
        v, u = np.mgrid[0:960, 0:1280].reshape(2, -1) / 1000.0
        depth = 2.0 + 0.3 * np.sin(3 * u) * np.cos(2 * v)
        organized = np.stack([(u - 0.64) * depth, (v - 0.48) * depth, depth], axis=1)
        organized[np.random.default_rng(1).uniform(size=len(organized)) < 0.3] = np.nan
        o3d.io.write_point_cloud(
            os.path.join(folder, "organized_compressed.pcd"),
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(organized)),
            compressed=True,
        )
        files.append(("organized_compressed.pcd", "Open3D"))
        try:
            import laspy
        except ImportError:
            laspy = None
        if laspy is not None:
            las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
            las.header.scales, las.header.offsets = [1e-4] * 3, [0.0] * 3
            las.x, las.y, las.z = cloud.T
            las.write(os.path.join(folder, "cloud.las"))
            files.append(("cloud.las", "laspy"))
        for name, writer in files:
            path = os.path.join(folder, name)
            count = len(io.read(path, drop_nonfinite=True))
            ours = best_seconds(lambda: io.read(path, drop_nonfinite=True), args.repeats)
            theirs = (
                best_seconds(lambda: o3d.io.read_point_cloud(path, remove_nan_points=True), args.repeats)
                if not name.endswith((".npy", ".csv", ".las"))
                else float("nan")
            )
            rows.append((name, f"{count:,} points", writer, os.path.getsize(path), ours, theirs, moved(path)))

        sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=args.sphere_resolution)
        sphere.compute_triangle_normals()
        for name in ("mesh.obj", "mesh.off", "mesh.stl", "mesh_ascii.stl", "mesh.ply", "mesh_ascii.ply"):
            path = os.path.join(folder, name)
            if name == "mesh_ascii.stl":  # Open3D writes binary STL only
                write_ascii_stl(
                    path, np.asarray(sphere.vertices)[np.asarray(sphere.triangles)], np.asarray(sphere.triangle_normals)
                )
            else:
                o3d.io.write_triangle_mesh(path, sphere, write_ascii="ascii" in name)
            ours = best_seconds(lambda: io.read(path), args.repeats)
            theirs = best_seconds(
                lambda: o3d.io.read_triangle_mesh(path).sample_points_uniformly(io.MESH_POINTS), args.repeats
            )
            rows.append(
                (
                    name,
                    f"{len(sphere.triangles):,} triangles",
                    "Open3D",
                    os.path.getsize(path),
                    ours,
                    theirs,
                    moved(path),
                )
            )

    print(
        "| file | holds | written by | MB | io.read (s) | Open3D (s) | io.move_file (s) |\n"
        "|---|---|---|---|---|---|---|"
    )
    show = lambda seconds: "-" if np.isnan(seconds) else f"{seconds:.2f}"  # noqa: E731
    for name, holds, writer, size, ours, theirs, move in rows:
        print(f"| {name} | {holds} | {writer} | {size / 1e6:.1f} | {ours:.2f} | {show(theirs)} | {show(move)} |")


if __name__ == "__main__":
    main()
