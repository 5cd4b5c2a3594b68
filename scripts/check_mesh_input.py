"""Registers a mesh onto a scan: each source scan of a real series meshed, written as STL, read back by
``io.read`` (points sampled over the surface) and registered onto the next scan, against the scans themselves.

    python scripts/check_mesh_input.py --scans ../shared/data/stanford_dragon_stand [--skip 1] [--pairs 15]

The mesh is Open3D's ball pivoting over the scan (radii 1, 2 and 4 times the median neighbour spacing), so its
surface is the scan's surface: what a CAD model or a reconstruction gives where it matches the scanned object.
Prints a markdown table (rotation error in degrees against the truth from the series' .conf, verdicts, seconds).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from dit_jax import io, metrics, registration
from dit_jax.data import scans as scan_data


def mesh_scan(points: np.ndarray, path: str) -> int:
    """Meshes ``points`` by ball pivoting and writes the mesh to ``path`` (STL); returns its triangle count."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    spacing = float(np.median(np.asarray(cloud.compute_nearest_neighbor_distance())))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    cloud.orient_normals_towards_camera_location(np.zeros(3))  # the scanner sits at its frame's origin
    radii = o3d.utility.DoubleVector([spacing, 2 * spacing, 4 * spacing])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    mesh.compute_triangle_normals()
    if not o3d.io.write_triangle_mesh(path, mesh):
        raise RuntimeError(f"could not write {path}")
    return len(mesh.triangles)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", required=True, help="a directory of scans with a Stanford .conf")
    parser.add_argument("--skip", type=int, default=1, help="pair scan i with scan i + skip")
    parser.add_argument("--pairs", type=int, default=None, help="the first N pairs (default: all)")
    args = parser.parse_args()

    model = registration.load()
    pairs = scan_data.scan_pairs(scan_data.load_scans(args.scans), skip=args.skip)[:args.pairs]
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for pair in pairs:
            path = os.path.join(folder, "source.stl")
            triangles = mesh_scan(pair.source, path)
            start = time.perf_counter()
            mesh_points = io.read(path)
            read_seconds = time.perf_counter() - start
            results = {"scan": model.register(pair.source, pair.target),
                       "mesh": model.register(mesh_points, pair.target)}
            errors = {k: float(metrics.rotation_error_deg(r.rotation, pair.rotation)) for k, r in results.items()}
            rows.append((pair.name, triangles, read_seconds, errors, results))
            print(f"{pair.name}: {triangles} triangles, scan {errors['scan']:.2f} deg, mesh {errors['mesh']:.2f} "
                  f"deg", flush=True)

    print("\n| pair | mesh triangles | read + sample (s) | scan onto scan: deg / verdict | mesh onto scan: deg / "
          "verdict | s (mesh) |\n|---|---|---|---|---|---|")
    for name, triangles, read_seconds, errors, results in rows:
        cells = [f"{errors[k]:.2f} / {'trusted' if results[k].verdict else 'suspect'}" for k in ("scan", "mesh")]
        print(f"| {name} | {triangles:,} | {read_seconds:.2f} | {cells[0]} | {cells[1]} | "
              f"{results['mesh'].seconds + results['mesh'].refine_seconds:.1f} |")
    for k in ("scan", "mesh"):
        e = np.array([r[3][k] for r in rows])
        trusted = [r[4][k].verdict for r in rows]
        print(f"{k}: median {np.median(e):.2f} deg, within 5 deg {int((e <= 5).sum())} of {len(e)}, "
              f"within 1 deg {int((e <= 1).sum())}, trusted {sum(trusted)}")


if __name__ == "__main__":
    main()
