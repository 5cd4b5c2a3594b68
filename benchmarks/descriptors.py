"""Descriptors on real rooms: inlier ratio and feature-match recall per scene and list, and seconds a fragment.

    python benchmarks/descriptors.py ../shared/data/3dmatch --record docs/descriptors.jsonl

For each scene of a folder of 3DMatch scenes (fragments with ``3DMatch/`` and ``3DLoMatch/`` lists): every
fragment on the grid local features use (the scene's voxel, normals facing the sensor), then each descriptor
of :data:`MEASURED` on it; for each pair of each list, the nearest-descriptor matches judged by the truth
(dit_jax.evaluators.descriptors). Prints one JSON record per scene and list, then a Markdown table;
``--record`` writes the records to a file, which the descriptor table of docs/features.md is generated from
(python tools/results_page.py).
"""

import argparse
import datetime
import json
import os
import pathlib
import time

import numpy as np

#: The descriptors measured: FPFH at one radius as it is, square-rooted, and the joined histograms.
MEASURED = ("fpfh", "fpfh_sqrt", "histograms")


def describe_all(clouds, viewpoint=(0.0, 0.0, 0.0)) -> tuple[list, dict, dict]:
    """Each cloud's keypoints (N_k, 3) and, per descriptor of :data:`MEASURED`, their descriptors; and the mean
    seconds a fragment each took (the keypoints' grid and normals not counted)."""
    from dit_jax.features import descriptors, keypoints

    prepared = keypoints.prepare_scans(clouds, viewpoint=viewpoint, descriptor="fpfh")
    keypoints, found, seconds = [], {name: [] for name in MEASURED}, dict.fromkeys(MEASURED, 0.0)
    for scan in prepared.scans:
        keypoints.append(np.asarray(scan.cloud.thinned.points))
        for name in ("fpfh", "histograms"):
            started = time.perf_counter()
            found[name].append(descriptors.describe(scan.cloud.thinned, prepared.voxel, name, viewpoint))
            seconds[name] += time.perf_counter() - started
        found["fpfh_sqrt"].append(np.sqrt(found["fpfh"][-1]))
    seconds["fpfh_sqrt"] = seconds["fpfh"]
    return keypoints, found, {name: s / len(clouds) for name, s in seconds.items()}


def measure_scene(folder: pathlib.Path) -> list[dict]:
    """One record per list of the scene in ``folder``."""
    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators import descriptors as quality

    sets = scans_lib.load_pair_sets(folder)
    fragments = {}
    for found in sets.values():
        for pair in found.pairs:
            source, target = pair.name.split("/")[-1].split("->")
            fragments[source], fragments[target] = pair.source, pair.target
    names = sorted(fragments)
    keypoints, described, seconds = describe_all([fragments[n] for n in names])
    row = {name: k for k, name in enumerate(names)}
    records = []
    for set_name, found in sets.items():
        record = {"benchmark": "descriptors", "date": datetime.date.today().isoformat(), "cpus": os.cpu_count()}
        record |= {"scene": folder.name, "set": set_name, "pairs": len(found.pairs), "seconds": seconds}
        for name in MEASURED:
            qualities = []
            for pair in found.pairs:
                s, t = (row[n] for n in pair.name.split("/")[-1].split("->"))
                qualities.append(
                    quality.match_quality(
                        keypoints[s], described[name][s], keypoints[t], described[name][t], pair.rotation,
                        pair.translation,
                    )
                )  # fmt: skip
            record[name] = quality.summary(qualities)
        records.append(record)
        print(json.dumps(record), flush=True)
    return records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a folder of 3DMatch scenes")
    parser.add_argument("--record", default=None, help="also write the records to this file (JSON lines)")
    args = parser.parse_args()
    scenes = sorted(p for p in pathlib.Path(args.scenes).iterdir() if p.is_dir())
    records = [r for scene in scenes for r in measure_scene(scene)]
    if args.record:
        with open(args.record, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in records)
    print("\n| scene | list | pairs | " + " | ".join(f"{n}: inlier ratio, FMR" for n in MEASURED) + " |")
    print("|---|---|---|" + "---|" * len(MEASURED))
    for r in records:
        cells = " | ".join(f"{r[n]['kept_inlier_ratio']:.3f}, {100 * r[n]['kept_fmr']:.0f} %" for n in MEASURED)
        print(f"| {r['scene']} | {r['set']} | {r['pairs']} | {cells} |")


if __name__ == "__main__":
    main()
