"""Which global candidate, and which way of choosing among candidates, registers rooms: on a seeded sample of
3DMatch pairs, the refined network (the pipeline without local features), the pipeline's registration by
local features (dit_jax.feature_match.match_one_way, one direction) and Open3D's room recipe (FPFH + RANSAC at 5 cm, dit_jax.baselines.room_recipe's global stage), each refined by GICP as
the pipeline refines scans; then what each choice rule keeps.

    python benchmarks/room_candidates.py ../shared/data/3dmatch --max-pairs 40

Rules: each candidate alone; the pipeline's rule between two candidates (the larger overlap,
dit_jax.icp.overlap within dit_jax.pipeline.CANDIDATE_OVERLAP point spacings); the largest overlap among all
three. Right: within 15 degrees and 0.3 m (the data's units). Prints one JSON record per list (pairs right
per rule, median seconds per candidate) and a Markdown table.
"""

import argparse
import datetime
import json
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a folder of 3DMatch scenes")
    parser.add_argument("--max-pairs", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from dit_jax import baselines, feature_match, geometry, icp, pipeline, registration
    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import is_right, sample_pairs

    model = registration.load(feature_candidate="off")
    records = []
    for set_name, found in scans_lib.load_pair_sets(args.scenes).items():
        pairs = sample_pairs(found, args.max_pairs, args.seed)
        right = {
            rule: 0 for rule in ("network", "features", "open3d", "network|features", "network|open3d", "all three")
        }
        seconds = {name: [] for name in ("network", "features", "open3d")}
        for pair in pairs:
            spacing = max(icp.point_spacing(pair.source), icp.point_spacing(pair.target))
            started = time.perf_counter()
            result = model.register(pair.source, pair.target)
            seconds["network"].append(time.perf_counter() - started)
            candidates = {"network": (result.rotation, result.translation)}
            for name in ("features", "open3d"):
                started = time.perf_counter()
                if name == "features":
                    match = feature_match.match_one_way(pair.source, pair.target, spacing=spacing)
                    start = (match.rotation, match.translation)
                else:
                    options = baselines.room_options()
                    start = baselines.ransac_on_features(
                        baselines.features(pair.source, options), baselines.features(pair.target, options), options
                    )
                own = icp.refine_gicp(pair.source, pair.target, *start, spacing=spacing)
                seconds[name].append(time.perf_counter() - started)
                candidates[name] = (own.rotation, own.translation)
            ok = {}
            for name, (rotation, translation) in candidates.items():
                row = {
                    "rot_err": geometry.rotation_angle_deg(np.asarray(rotation).T @ pair.rotation),
                    "trans_err": float(np.linalg.norm(translation - pair.translation)),
                }
                ok[name] = is_right(row, found.criterion)
            names = list(candidates)
            shares = dict(
                zip(
                    names,
                    icp.overlap(
                        pair.source, pair.target, [candidates[n] for n in names], pipeline.CANDIDATE_OVERLAP * spacing
                    ),
                )
            )
            pick = lambda among: max(among, key=lambda n: (shares[n], n == "network"))
            right["network"] += ok["network"]
            right["features"] += ok["features"]
            right["open3d"] += ok["open3d"]
            right["network|features"] += ok[pick(["network", "features"])]
            right["network|open3d"] += ok[pick(["network", "open3d"])]
            right["all three"] += ok[pick(names)]
        record = {
            "benchmark": "room_candidates",
            "date": datetime.date.today().isoformat(),
            "set": set_name,
            "pairs": len(pairs),
            "seed": args.seed,
            "right": right,
            "median_seconds": {k: float(np.median(v)) for k, v in seconds.items()},
        }
        print(json.dumps(record), flush=True)
        records.append(record)
    rules = list(records[0]["right"])
    print(
        "\n| list | pairs | "
        + " | ".join(rules)
        + " | median s: network, features, open3d |\n|---|---|"
        + "---|" * len(rules)
        + "---|"
    )
    for r in records:
        s = r["median_seconds"]
        print(
            f"| {r['set']} | {r['pairs']} | "
            + " | ".join(str(r["right"][k]) for k in rules)
            + f" | {s['network']:.2f}, {s['kiss_matcher']:.2f}, {s['open3d']:.2f} |"
        )


if __name__ == "__main__":
    main()
