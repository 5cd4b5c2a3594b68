"""DIT's ICP refinement (:func:`dit_jax.geometry.icp_refine.refine`, as ``register(refine="icp")`` runs it) started at the exact
truth, on ModelNet40 unseen test pairs of every setting. The refinement only leaves its start for a motion
that fits the clouds better (:func:`dit_jax.geometry.icp.trimmed_fit`), so every pair that ends more than 1 degree
off here is one whose points prefer a pose more than 1 degree from the truth: what "ends within 1 degree"
can ask of DIT + ICP on that setting.

    python benchmarks/icp_from_truth.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --pairs 100
    python benchmarks/icp_from_truth.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --pairs 100 --compare

Prints a markdown table: median / mean / worst rotation error after refinement and how many pairs end more
than 1 degree off. Point count: the shipped weights' (as evaluate.py uses). ``--compare`` prints a second
table: how many pairs each other local objective, started at the truth, leaves by more than 1 degree --
point-to-plane ICP (coarse to fine, as in :data:`dit_jax.geometry.icp_refine.REFINE_CANDIDATES`) and Open3D's generalized
ICP (plane-to-plane, Segal et al. 2009; through Open3D) -- so a reader can see whether any
of them holds the truth where the refinement's point fit does not. The last line is one JSON record of it all.
"""

import argparse
import datetime
import json

import numpy as np

from dit_jax.data import pairs as pairs_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.geometry import icp, icp_refine
from dit_jax.geometry.rigid import rotation_angle_deg
from dit_jax.pipeline import registration


def _generalized_icp(src, tgt, rotation, translation, distances):
    """Open3D's generalized ICP, one stage per pairing distance; returns the rotation (3, 3)."""
    import open3d as o3d

    registration_lib = o3d.pipelines.registration
    cloud = lambda x: o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(x, np.float64)))
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = rotation, translation
    for distance in distances:
        motion = registration_lib.registration_generalized_icp(
            cloud(src),
            cloud(tgt),
            distance,
            motion,
            registration_lib.TransformationEstimationForGeneralizedICP(),
            registration_lib.ICPConvergenceCriteria(1e-9, 1e-9, 60),
        ).transformation
    return motion[:3, :3]


#: The local objectives ``--compare`` starts at the truth: name -> (src, tgt, R, t) -> rotation (3, 3).
OBJECTIVES = {
    "refinement (shipped)": lambda s, g, r, t: icp_refine.refine(s, g, r, t).rotation,
    "point-to-plane 0.1/0.05": lambda s, g, r, t: (
        icp.icp(s, g, r, t, distances=(0.1, 0.05), method="point_to_plane").rotation
    ),
    "point-to-plane 0.1/0.05/0.02": lambda s, g, r, t: (
        icp.icp(s, g, r, t, distances=(0.1, 0.05, 0.02), method="point_to_plane").rotation
    ),
    "generalized ICP 0.1/0.05 (Open3D)": lambda s, g, r, t: _generalized_icp(s, g, r, t, (0.1, 0.05)),
    "generalized ICP 0.1 (Open3D)": lambda s, g, r, t: _generalized_icp(s, g, r, t, (0.1,)),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", required=True, help="ModelNet40 in the h5 layout")
    parser.add_argument("--pairs", type=int, default=100, help="the first pairs of each setting")
    parser.add_argument(
        "--compare",
        action="store_true",
        help="also start point-to-plane and generalized ICP at the truth (needs Open3D)",
    )
    args = parser.parse_args()
    n_points = registration.load().settings.n_points
    settings = list(pairs_lib.SETTINGS)
    shapes = shapes_lib.load_shapes(
        args.data_dir, "test", n_points=pairs_lib.shape_points(args.data_dir, n_points, settings)
    )
    objectives = OBJECTIVES if args.compare else {"refinement (shipped)": OBJECTIVES["refinement (shipped)"]}
    print(
        f"{datetime.date.today().isoformat()}: `python benchmarks/icp_from_truth.py --data-dir {args.data_dir} "
        f"--pairs {args.pairs}{' --compare' if args.compare else ''}` (unseen categories, {n_points} points)\n"
    )
    errors = {name: {} for name in objectives}
    for setting in settings:
        dataset = pairs_lib.PairDataset(shapes, pairs_lib.PairConfig(setting=setting, unseen=True, n_points=n_points))
        for name, run in objectives.items():
            found = []
            for n in range(min(args.pairs, len(dataset))):
                pair = dataset[n]
                truth = pair["R"].astype(np.float64)
                rotation = run(pair["src"], pair["tgt"], truth, pair["t"].astype(np.float64))
                found.append(rotation_angle_deg(rotation.T @ truth))
            errors[name][setting] = np.asarray(found)
    print("| setting | median deg | mean deg | worst deg | more than 1 deg off |\n|---|---|---|---|---|")
    for setting, found in errors["refinement (shipped)"].items():
        print(
            f"| {setting} | {np.median(found):.3f} | {found.mean():.3f} | {found.max():.2f} | "
            f"{int(np.sum(found > 1.0))} of {len(found)} |"
        )
    if args.compare:
        print("\nStarted at the truth, pairs each objective leaves by more than 1 degree (median error, deg):\n")
        print("| setting | " + " | ".join(objectives) + " |\n|---|" + "---|" * len(objectives))
        for setting in settings:
            cells = [
                f"{int(np.sum(errors[name][setting] > 1.0))} ({np.median(errors[name][setting]):.2f})"
                for name in objectives
            ]
            print(f"| {setting} | " + " | ".join(cells) + " |")
    print(
        json.dumps(
            {
                "benchmark": "icp_from_truth",
                "date": datetime.date.today().isoformat(),
                "pairs": args.pairs,
                "n_points": n_points,
                "more_than_1_deg": {
                    name: {s: int(np.sum(e > 1.0)) for s, e in per.items()} for name, per in errors.items()
                },
                "median_deg": {name: {s: float(np.median(e)) for s, e in per.items()} for name, per in errors.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
