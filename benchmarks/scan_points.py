"""Where local features should run first: the default pipeline with and without them on scans thinned to a
given number of points.

    python benchmarks/scan_points.py ../shared/data/stanford_dragon_stand --points 2500 4000

For each folder of scans with known poses, each pair of its series (scan i with i + 1 and i + 2) with both
clouds thinned uniformly at random (seed 0) to each ``--points``: the shipped weights with
``feature_candidate="on"`` and ``"off"``, each result right within 5 degrees or not, with its verdict's level.
The default's threshold is ``dit_jax.settings.SCAN_POINTS``. Prints one JSON record per folder and size, then
a Markdown table.
"""

import argparse
import datetime
import json
import os

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses (a series)")
    parser.add_argument("--points", type=int, nargs="+", default=[2500, 4000])
    args = parser.parse_args()

    from dit_jax import geometry, registration
    from dit_jax.data import scans as scans_lib

    models = {"on": registration.load(feature_candidate="on"), "off": registration.load(feature_candidate="off")}
    records = []
    for folder in args.scans:
        series = scans_lib.load_scans(folder)
        pairs = [p for skip in (1, 2) for p in scans_lib.scan_pairs(series, skip=skip)]
        for points in args.points:
            rng = np.random.default_rng(0)
            counts = {k: dict(pairs=0, right=0, trusted=0, trusted_right=0, exit0=0, exit0_right=0) for k in models}
            for pair in pairs:
                src = pair.source[rng.choice(len(pair.source), min(points, len(pair.source)), replace=False)]
                tgt = pair.target[rng.choice(len(pair.target), min(points, len(pair.target)), replace=False)]
                for name, model in models.items():
                    result = model.register(src, tgt)
                    right = geometry.rotation_angle_deg(result.rotation.T @ pair.rotation) <= 5.0
                    c = counts[name]
                    c["pairs"] += 1
                    c["right"] += right
                    c["trusted"] += result.level == "trusted"
                    c["trusted_right"] += right and result.level == "trusted"
                    c["exit0"] += result.level != "probably wrong"
                    c["exit0_right"] += right and result.level != "probably wrong"
            record = {
                "benchmark": "scan_points",
                "date": datetime.date.today().isoformat(),
                "data": os.path.basename(os.path.normpath(folder)),
                "points": points,
                "features_on": counts["on"],
                "features_off": counts["off"],
            }
            records.append(record)
            print(json.dumps(record), flush=True)
    print(
        "\n| data | points a cloud | pairs | features first: right, trusted (right) | network only: right, trusted (right) |"
    )
    print("|---|---|---|---|---|")
    for r in records:
        on, off = r["features_on"], r["features_off"]
        print(
            f"| {r['data']} | {r['points']:,} | {on['pairs']} | {on['right']}, {on['trusted']} ({on['trusted_right']}) "
            f"| {off['right']}, {off['trusted']} ({off['trusted_right']}) |"
        )


if __name__ == "__main__":
    main()
