"""The feature match alone (no refinement) at several voxels: pairs within their criterion and seconds.

    python benchmarks/feature_voxel.py ../shared/data/stanford_dragon_stand ../shared/data/3dmatch_redkitchen \\
        ../shared/data/lidar_pair --voxels 2 2.5 3 4 6 8

For each folder of scans with known poses and each pair set: dit_jax.feature_match.match_one_way at a voxel of V
point spacings (instead of its own choice, dit_jax.feature_match.feature_voxel), for each V. A pair counts
where the estimate is within the set's benchmark criterion, else within 5 degrees. One JSON record per pair
set and voxel, then a Markdown table.
"""

import argparse
import datetime
import json
import os
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument(
        "--voxels", nargs="+", type=float, default=[2.0, 3.0, 4.0, 8.0], help="voxels in point spacings"
    )
    args = parser.parse_args()

    from dit_jax import feature_match, geometry, icp
    from dit_jax.data import scans as scans_lib

    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            degrees, distance = found.criterion or (5.0, np.inf)
            spacings = [max(icp.point_spacing(p.source), icp.point_spacing(p.target)) for p in found.pairs]
            for voxel in args.voxels:
                right, seconds = 0, []
                for pair, spacing in zip(found.pairs, spacings):
                    started = time.perf_counter()
                    match = feature_match.match_one_way(pair.source, pair.target, spacing=spacing, voxel_spacings=voxel)
                    seconds.append(time.perf_counter() - started)
                    right += (
                        geometry.rotation_angle_deg(match.rotation.T @ pair.rotation) <= degrees
                        and np.linalg.norm(match.translation - pair.translation) <= distance
                    )
                record = {
                    "benchmark": "feature_voxel",
                    "date": datetime.date.today().isoformat(),
                    "data": os.path.basename(os.path.normpath(folder)),
                    "set": set_name,
                    "pairs": len(found.pairs),
                    "voxel_spacings": voxel,
                    "right": int(right),
                    "median_s": float(np.median(seconds)),
                }
                print(json.dumps(record), flush=True)
                records.append(record)
    print("\n| data | pairs | voxel (spacings) | right | s / pair (median) |\n|---|---|---|---|---|")
    for r in records:
        print(
            f"| {r['data']} {r['set']} | {r['pairs']} | {r['voxel_spacings']:g} | {r['right']} | {r['median_s']:.2f} |"
        )


if __name__ == "__main__":
    main()
