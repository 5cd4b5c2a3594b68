"""How the pipeline should choose between the refined network and the refined feature match: on every pair of
real scans, which of the two is right, and which one each criterion would keep.

    python benchmarks/candidate_choice.py ../shared/data/stanford_dragon_stand ../shared/data/3dmatch_redkitchen

For each pair: the shipped weights without the second candidate (the refined network's result), and the
feature match (dit_jax.feature_match) refined by the same refinement; then the two criteria, each on the
caller's clouds: the trimmed fit (dit_jax.icp.fits_better, the closest 70 % of the gaps) and the overlap
(dit_jax.icp.overlap: the share of source points within dit_jax.pipeline.CANDIDATE_OVERLAP point spacings
of the target). Prints one JSON record per pair set: pairs where the two candidates differ by more than
5 degrees, and how many of those each criterion settles on the right one; then a Markdown table.
"""

import argparse
import datetime
import json
import os

import numpy as np

DIFFERENT_DEG = 5.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    args = parser.parse_args()

    from dit_jax import feature_match, geometry, icp, pipeline, registration
    from dit_jax.data import scans as scans_lib

    model = registration.load(feature_candidate="off")
    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            differ = right_by_fit = right_by_overlap = 0
            for pair in found.pairs:
                result = model.register(pair.source, pair.target)
                method = result.refinement or "icp"
                spacing = max(icp.point_spacing(pair.source), icp.point_spacing(pair.target))
                match = feature_match.match_one_way(pair.source, pair.target, spacing=spacing)
                if method == "gicp":
                    own = icp.refine_gicp(pair.source, pair.target, match.rotation, match.translation, spacing=spacing)
                else:
                    scale = float(np.linalg.norm(pair.target - pair.target.mean(axis=0), axis=1).max())
                    own = icp.refine(pair.source, pair.target, match.rotation, match.translation, scale=scale)
                errors = [
                    geometry.rotation_angle_deg(np.asarray(r).T @ pair.rotation)
                    for r in (result.rotation, own.rotation)
                ]
                if abs(errors[0] - errors[1]) <= DIFFERENT_DEG:
                    continue
                differ += 1
                right = int(np.argmin(errors))  # 0: the network's, 1: the feature match's
                motions = [(result.rotation, result.translation), (own.rotation, own.translation)]
                by_fit = int(icp.fits_better(pair.source, pair.target, motions[1], motions[0]))
                shares = icp.overlap(pair.source, pair.target, motions, pipeline.CANDIDATE_OVERLAP * spacing)
                by_overlap = int(shares[1] > shares[0])
                right_by_fit += by_fit == right
                right_by_overlap += by_overlap == right
            record = {
                "benchmark": "candidate_choice",
                "date": datetime.date.today().isoformat(),
                "data": os.path.basename(os.path.normpath(folder)),
                "set": set_name,
                "pairs": len(found.pairs),
                "candidates_differ": differ,
                "trimmed_fit_right": right_by_fit,
                "overlap_right": right_by_overlap,
            }
            print(json.dumps(record), flush=True)
            records.append(record)
    print(
        f"\n| data | pairs | candidates more than {DIFFERENT_DEG:g} deg apart | the trimmed fit keeps the right one "
        "| the overlap keeps the right one |\n|---|---|---|---|---|"
    )
    for r in records:
        print(
            f"| {r['data']} {r['set']} | {r['pairs']} | {r['candidates_differ']} | {r['trimmed_fit_right']} | "
            f"{r['overlap_right']} |"
        )


if __name__ == "__main__":
    main()
