"""How far apart the two directions of the registration by local features land, on right and wrong results:
the evidence behind the verdict's bounds on scans (InferenceSettings.max_disagreement_features and
max_offset_features).

    python benchmarks/feature_agreement.py ../shared/data/3dmatch ../shared/data/stanford_dragon_stand \\
        --max-pairs 40

For each folder of scans with known poses and each of its pair sets (a seeded sample of --max-pairs per
benchmark list, the first pairs of a series): dit_jax.feature_match.register_both_ways as the pipeline calls
it; the kept direction (the larger overlap) is right by the data's criterion (3DMatch: the benchmark's RMSE
at most 0.2 m; otherwise within 5 degrees). For each pair of bounds (degrees, point spacings): how many results
the bounds trust, how many of those are right, and how many of the wrong ones they leave flagged, per pair
set and per scene, so a bound can be read with one scene left out. Prints one JSON record per pair set, then
Markdown tables.
"""

import argparse
import datetime
import json

import numpy as np

BOUNDS = ((1.0, 2.0), (1.0, 3.0), (2.0, 4.0), (2.0, 6.0), (3.0, 8.0), (4.0, 12.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument("--max-pairs", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from dit_jax import feature_match, geometry
    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import sample_pairs

    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            rows = []
            for pair in sample_pairs(found, args.max_pairs, args.seed):
                estimate = feature_match.register_both_ways(pair.source, pair.target, seed=args.seed)
                if estimate is None:
                    rows.append(dict(scene=pair.scene, right=False, disagreement=np.inf, offset=np.inf, seconds=0.0))
                    continue
                rotation, translation = estimate.kept
                if pair.info is not None:
                    rmse = scans_lib.benchmark_rmse(rotation, translation, pair)
                    right = bool(rmse <= scans_lib.BENCHMARK_RMSE)
                else:
                    right = bool(geometry.rotation_angle_deg(rotation.T @ pair.rotation) <= 5.0)
                rows.append(
                    dict(
                        scene=pair.scene,
                        right=right,
                        disagreement=estimate.disagreement,
                        offset=estimate.offset,
                        seconds=estimate.seconds,
                    )
                )
            scenes = sorted({r["scene"] for r in rows})
            record = {
                "data": folder.rstrip("/").split("/")[-1],
                "set": set_name,
                "pairs": len(rows),
                "right": sum(r["right"] for r in rows),
                "median_s": float(np.median([r["seconds"] for r in rows])),
                "bounds": [],
                "date": datetime.date.today().isoformat(),
            }
            for degrees, spacings in BOUNDS:
                entry = {"degrees": degrees, "spacings": spacings}
                for scene in [None, *scenes] if len(scenes) > 1 else [None]:
                    subset = [r for r in rows if scene is None or r["scene"] == scene]
                    trusted = [r["disagreement"] <= degrees and r["offset"] <= spacings for r in subset]
                    counts = {
                        "trusted": int(sum(trusted)),
                        "trusted_right": int(sum(t and r["right"] for t, r in zip(trusted, subset))),
                        "wrong": int(sum(not r["right"] for r in subset)),
                        "wrong_flagged": int(sum(not t and not r["right"] for t, r in zip(trusted, subset))),
                    }
                    entry[scene or "all"] = counts
                record["bounds"].append(entry)
            records.append(record)
            print(json.dumps(record), flush=True)

    print("\n| data | set | pairs | right | bounds (deg, spacings) | trusted | of those right | wrong flagged |")
    print("|---|---|---|---|---|---|---|---|")
    for record in records:
        for entry in record["bounds"]:
            counts = entry["all"]
            print(
                f"| {record['data']} | {record['set']} | {record['pairs']} | {record['right']} | "
                f"{entry['degrees']:g}, {entry['spacings']:g} | {counts['trusted']} | {counts['trusted_right']} | "
                f"{counts['wrong_flagged']} of {counts['wrong']} |"
            )


if __name__ == "__main__":
    main()
