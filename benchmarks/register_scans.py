"""The default pipeline beside FPFH + RANSAC + ICP on real scans: pairs registered and seconds per pair.

    python benchmarks/register_scans.py ../shared/data/3dmatch_redkitchen ../shared/data/lidar_pair \\
        ../shared/data/stanford_dragon_stand
    python benchmarks/register_scans.py ../shared/data/3dmatch --max-pairs 40 --baseline open3d_room_5cm

For each folder of scans with known poses (any layout of :mod:`dit_jax.data.scans`) and each of its pair sets:
the shipped weights through `Registrar.register` with their own settings (sampling, network both ways,
refinement, verdict and, where the result is not trusted, the second candidate), timed whole per pair after
one untimed call that compiles; and a baseline as evaluate.py runs it (through Open3D): by default
Open3D's FPFH + RANSAC + ICP at its tuned options, ``--baseline open3d_room_5cm`` Open3D's room recipe.
``--max-pairs``: a seeded sample of a benchmark's list (the first pairs of a series), as evaluate.py takes.
A pair is registered by its benchmark's criterion (dit_jax.data.scans.CRITERIA), else within 5 degrees. Prints one JSON record per pair set (``confirmed_max_s``: the slowest pair whose first
candidate was trusted, the figure the 1.5 s target is about), then a Markdown table.
"""

import argparse
import datetime
import json
import os
import time

import numpy as np


def registered(rotation, translation, pair, criterion) -> bool:
    from dit_jax import geometry

    degrees, distance = criterion or (5.0, np.inf)
    return bool(
        geometry.rotation_angle_deg(np.asarray(rotation).T @ pair.rotation) <= degrees
        and np.linalg.norm(np.asarray(translation) - pair.translation) <= distance
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument("--no-baseline", action="store_true", help="time the pipeline alone")
    parser.add_argument("--baseline", default="fpfh_ransac_icp", help="a name of dit_jax.baselines.SCAN_BASELINES")
    parser.add_argument("--max-pairs", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0, help="the sample's seed")
    args = parser.parse_args()
    baseline = args.baseline

    from dit_jax import registration
    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import register_baseline, sample_pairs

    model = registration.load()
    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            pairs = sample_pairs(found, args.max_pairs, args.seed)
            model.register(pairs[0].source, pairs[0].target)  # compiles (or warms) once per folder's sizes
            pipeline_s, pipeline_ok, confirmed_s, trusted, trusted_right = [], 0, [], 0, 0
            baseline_s, baseline_ok = [], 0
            for pair in pairs:
                started = time.perf_counter()
                result = model.register(pair.source, pair.target)
                pipeline_s.append(time.perf_counter() - started)
                ok = registered(result.rotation, result.translation, pair, found.criterion)
                pipeline_ok += ok
                trusted += result.verdict
                trusted_right += result.verdict and ok
                if (result.first or result).verdict:
                    confirmed_s.append(pipeline_s[-1])
                if not args.no_baseline:
                    rotation, translation, seconds = register_baseline(baseline, pair.source, pair.target)
                    baseline_s.append(seconds)
                    baseline_ok += registered(rotation, translation, pair, found.criterion)
            record = {
                "benchmark": "register_scans",
                "date": datetime.date.today().isoformat(),
                "cpus": os.cpu_count(),
                "data": os.path.basename(os.path.normpath(folder)),
                "set": set_name,
                "pairs": len(pairs),
                "points": [
                    min(min(len(p.source), len(p.target)) for p in pairs),
                    max(max(len(p.source), len(p.target)) for p in pairs),
                ],
                "criterion": found.criterion,
                "pipeline": {
                    "registered": int(pipeline_ok),
                    "trusted": int(trusted),
                    "trusted_right": int(trusted_right),
                    "median_s": float(np.median(pipeline_s)),
                    "max_s": float(np.max(pipeline_s)),
                    "confirmed_pairs": len(confirmed_s),
                    "confirmed_max_s": float(np.max(confirmed_s)) if confirmed_s else None,
                },
            }
            if baseline_s:
                record[baseline] = {
                    "registered": int(baseline_ok),
                    "median_s": float(np.median(baseline_s)),
                    "max_s": float(np.max(baseline_s)),
                }
            print(json.dumps(record), flush=True)
            records.append(record)
    print(f"\n{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, shipped weights with their settings\n")
    print(
        f"| data | pairs | points a cloud | pipeline: registered, trusted (right) | pipeline s / pair: median, "
        f"max, max where the first candidate was confirmed | {baseline}: registered | {baseline} s / pair: "
        "median, max |\n|---|---|---|---|---|---|---|"
    )
    for r in records:
        p, b = r["pipeline"], r.get(baseline)
        confirmed = "-" if p["confirmed_max_s"] is None else f"{p['confirmed_max_s']:.2f}"
        print(
            f"| {r['data']} {r['set']} | {r['pairs']} | {r['points'][0]:,}-{r['points'][1]:,} | "
            f"{p['registered']}, {p['trusted']} ({p['trusted_right']}) | {p['median_s']:.2f}, {p['max_s']:.2f}, "
            f"{confirmed} | " + (f"{b['registered']} | {b['median_s']:.2f}, {b['max_s']:.2f} |" if b else "- | - |")
        )


if __name__ == "__main__":
    main()
