"""The global estimator on rooms, step by step, beside Open3D's RANSAC on the same features.

    python benchmarks/global_estimator.py ../shared/data/3dmatch --max-pairs 40

For each pair set of a folder of scans with known poses (a seeded sample of --max-pairs per benchmark list),
one direction per pair (source onto target), each step of dit_jax.features.matching timed on its own: both clouds'
normals and FPFH features (``features``), the nearest-feature matches (``matching``), the compatibility
estimator (``compatibility``: dit_jax.features.compatibility.estimate_motions, its tables, seeds and hypotheses), the choice
among its hypotheses on the thinned clouds with the rival (``scoring``), ICP, and the turned twins (``twin``).
Beside it, on the same features, Open3D's ``registration_ransac_based_on_feature_matching`` (mutual filter,
1,000,000 draws, confidence 0.999, edge check 0.9, distance 1.5 voxels: the tutorial's RANSAC). A motion counts
as found where it lies within the data's criterion of the truth (3DMatch: 15 degrees and 0.3 m) before any ICP.
Prints one JSON record per pair set (medians per step), then a Markdown table.
"""

import argparse
import datetime
import json
import os
import time

import numpy as np

from dit_jax.training.precision import cpu_model

STEPS = ("features", "matching", "compatibility", "scoring", "icp", "twin")


def open3d_ransac(source, target, voxel: float) -> np.ndarray:
    """Open3D's RANSAC on the two clouds' features, as its tutorial runs it: 4 x 4 motion."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(0)
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
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
            reg.RANSACConvergenceCriteria(1_000_000, 0.999),
        )
    return np.asarray(found.transformation)


def timed_steps(pair) -> tuple[dict, np.ndarray, np.ndarray] | None:
    """Each step's seconds for one direction of ``pair``, the chosen motion before ICP, and Open3D's: or None
    where the clouds have too few features."""
    from dit_jax.features import compatibility, keypoints, twins
    from dit_jax.features import matching as fm

    src, tgt, _, voxel, enough = keypoints.prepare(pair.source, pair.target, None, 0, keypoints.VOXEL_SPACINGS)
    if not enough:
        return None
    seconds, clock = {}, time.perf_counter()

    def lap(step):
        nonlocal clock
        now = time.perf_counter()
        seconds[step], clock = now - clock, now

    source, target = keypoints.Cloud(src, voxel), keypoints.Cloud(tgt, voxel)
    lap("features")
    matches, _ = fm._matches(source, target)
    lap("matching")
    src_matched = np.asarray(source.thinned.points)[matches[:, 0]]
    tgt_matched = np.asarray(target.thinned.points)[matches[:, 1]]
    found = compatibility.estimate_motions(src_matched, tgt_matched, fm.MATCH_VOXELS * voxel)
    lap("compatibility")
    motion, _, _ = fm._choose(source, target, src_matched, tgt_matched, found, voxel)
    lap("scoring")
    refined = fm._icp(source, target, motion, voxel)
    lap("icp")
    twins.twin_fit(source, target, voxel, fm._split(refined))
    lap("twin")
    started = time.perf_counter()
    theirs = open3d_ransac(source, target, voxel)
    seconds["open3d_ransac"] = time.perf_counter() - started
    return seconds, motion, theirs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument("--max-pairs", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0, help="the sample's seed")
    args = parser.parse_args()

    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import sample_pairs
    from dit_jax.geometry import rigid

    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            degrees, metres = found.criterion or (5.0, np.inf)
            pairs = sample_pairs(found, args.max_pairs, args.seed)
            timed_steps(pairs[0])  # compiles the estimator's programs once
            seconds, right = [], {"ours": 0, "open3d_ransac": 0}
            for pair in pairs:
                timed = timed_steps(pair)
                if timed is None:
                    continue
                seconds.append(timed[0])
                for name, motion in zip(right, timed[1:]):
                    right[name] += bool(
                        rigid.rotation_angle_deg(motion[:3, :3].T @ pair.rotation) <= degrees
                        and np.linalg.norm(motion[:3, 3] - pair.translation) <= metres
                    )
            medians = {step: float(np.median([s[step] for s in seconds])) for step in seconds[0]}
            record = {
                "benchmark": "global_estimator",
                "date": datetime.date.today().isoformat(),
                "cpus": os.cpu_count(),
                "cpu": cpu_model(),
                "data": os.path.basename(os.path.normpath(folder)),
                "set": set_name,
                "pairs": len(seconds),
                "found": right,
                "median_s": medians,
                "ours_median_s": float(np.median([sum(s[step] for step in STEPS) for s in seconds])),
            }
            records.append(record)
            print(json.dumps(record), flush=True)
    print(f"\n{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, {cpu_model()}, one direction per pair\n")
    print(
        "| data | pairs | found: ours, Open3D RANSAC | "
        + " | ".join(f"{s} (median s)" for s in STEPS)
        + " | all | Open3D RANSAC |"
    )
    print("|---|---|---|" + "---|" * (len(STEPS) + 2))
    for r in records:
        m = r["median_s"]
        print(
            f"| {r['data']} {r['set']} | {r['pairs']} | {r['found']['ours']}, {r['found']['open3d_ransac']} | "
            + " | ".join(f"{m[s]:.3f}" for s in STEPS)
            + f" | {r['ours_median_s']:.2f} | {m['open3d_ransac']:.2f} |"
        )


if __name__ == "__main__":
    main()
