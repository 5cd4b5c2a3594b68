"""RANSAC on rooms: Open3D's RANSAC on features beside the project's (dit_jax.feature_match), one direction each.

    python benchmarks/ransac.py ../shared/data/3dmatch --max-pairs 40

For each pair set of a folder of scans with known poses (a seeded sample of --max-pairs per benchmark list):
both clouds' FPFH features once, as dit_jax.feature_match computes them; then, timed side by side on the same
features, Open3D's ``registration_ransac_based_on_feature_matching`` (mutual filter, its own matching, the
pipeline's draws, confidence and checks) and the project's matching plus RANSAC. A motion counts as found
where it lies within the data's criterion of the truth (3DMatch: 15 degrees and 0.3 m), before any ICP.
Prints one JSON record per pair set, then a Markdown table.
"""

import argparse
import datetime
import json
import os
import platform
import time

import numpy as np


def open3d_ransac(source, target, voxel: float, seed: int) -> np.ndarray:
    """Open3D's RANSAC on the two clouds' features, as the pipeline called it before its own: 4 x 4 motion."""
    import open3d as o3d

    from dit_jax import feature_match

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    distance = 1.5 * voxel
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        found = reg.registration_ransac_based_on_feature_matching(
            source.thinned,
            target.thinned,
            source.features,
            target.features,
            True,
            distance,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [
                reg.CorrespondenceCheckerBasedOnEdgeLength(feature_match.EDGE_SIMILARITY),
                reg.CorrespondenceCheckerBasedOnDistance(distance),
            ],
            reg.RANSACConvergenceCriteria(feature_match.RANSAC_DRAWS, feature_match.RANSAC_CONFIDENCE),
        )
    return np.asarray(found.transformation)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument("--max-pairs", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0, help="the sample's seed")
    args = parser.parse_args()

    from dit_jax import feature_match, geometry
    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import sample_pairs

    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            degrees, metres = found.criterion or (5.0, np.inf)
            seconds = {"open3d": [], "ours": []}
            right = {"open3d": 0, "ours": 0}
            for pair in sample_pairs(found, args.max_pairs, args.seed):
                src, tgt, _, voxel, enough = feature_match._prepare(
                    pair.source, pair.target, None, 0, feature_match.VOXEL_SPACINGS
                )
                if not enough:
                    continue
                source, target = feature_match._Cloud(src, voxel), feature_match._Cloud(tgt, voxel)
                started = time.perf_counter()
                motions = {"open3d": open3d_ransac(source, target, voxel, 0)}
                seconds["open3d"].append(time.perf_counter() - started)
                started = time.perf_counter()
                matches, _ = feature_match._matches(source, target)
                motions["ours"] = feature_match._ransac(source, target, matches, voxel, 0)[0]
                seconds["ours"].append(time.perf_counter() - started)
                for name, motion in motions.items():
                    right[name] += bool(
                        geometry.rotation_angle_deg(motion[:3, :3].T @ pair.rotation) <= degrees
                        and np.linalg.norm(motion[:3, 3] - pair.translation) <= metres
                    )
            record = {
                "benchmark": "ransac",
                "date": datetime.date.today().isoformat(),
                "cpus": os.cpu_count(),
                "cpu": platform.processor() or platform.machine(),
                "data": os.path.basename(os.path.normpath(folder)),
                "set": set_name,
                "pairs": len(seconds["ours"]),
                **{
                    name: {
                        "found": right[name],
                        "median_s": float(np.median(seconds[name])),
                        "max_s": float(np.max(seconds[name])),
                    }
                    for name in seconds
                },
            }
            records.append(record)
            print(json.dumps(record), flush=True)
    print(f"\n{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, one direction per pair\n")
    print("| data | pairs | Open3D: found, median s, max s | dit_jax.feature_match: found, median s, max s |")
    print("|---|---|---|---|")
    for r in records:
        o, m = r["open3d"], r["ours"]
        print(
            f"| {r['data']} {r['set']} | {r['pairs']} | {o['found']}, {o['median_s']:.2f}, {o['max_s']:.2f} "
            f"| {m['found']}, {m['median_s']:.2f}, {m['max_s']:.2f} |"
        )


if __name__ == "__main__":
    main()
