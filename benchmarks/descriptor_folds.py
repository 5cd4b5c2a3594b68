"""The learned descriptor with each scene left out of its training in turn: inlier ratio and feature-match
recall on the scene it never saw, beside FPFH and the joined histograms measured in the same run.

    python benchmarks/descriptor_folds.py ../shared/data/3dmatch --workdirs runs --record docs/descriptor_folds.jsonl

For each scene of a folder of 3DMatch scenes: ``python train.py --config configs/features.py
--config.holdout=SCENE`` as the library runs it (dit_jax.training.descriptor.train; an existing run in
WORKDIRS/features-SCENE is resumed, so a finished one is only validated again), then one JSON record per scene
and list; a last record sums the lists over the scenes (means weighted by pairs). ``--record`` writes the
records to a file, which the fold table of docs/features.md is generated from (python tools/results_page.py).
Registration with each fold's weights on its left-out scene:

    python benchmarks/register_scans.py ../shared/data/3dmatch/hotel3 --no-baseline \\
        --descriptor runs/features-hotel3/descriptor --pairs-out runs/folds_pairs.jsonl
"""

import argparse
import datetime
import json
import os
import platform
import time

MEASURED = ("fpfh", "histograms", "learned")


def cpu_model() -> str:
    """lscpu's model name (from /proc/cpuinfo), else the machine's architecture."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.machine()


def run_fold(folder: str, scene: str, workdir: str, steps: int | None) -> tuple[dict, float]:
    """One fold's training result (dit_jax.training.descriptor.train) and its seconds."""
    from dit_jax import training
    from dit_jax.training import descriptor

    config = training.load_config(
        os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "configs", "features.py")
    )
    changes = {"data_dir": folder, "holdout": scene} | ({"steps": steps} if steps else {})
    config = type(config).from_json(config.to_json() | changes)
    started = time.perf_counter()
    resume = os.path.isdir(os.path.join(workdir, "checkpoints"))
    result = descriptor.train(config, workdir, resume=resume, progress=False)
    return result, time.perf_counter() - started


def summed(records: list[dict]) -> dict:
    """Per list, the pair-weighted means of each descriptor's figures over the scenes' records."""
    out = {}
    for listed in sorted({r["set"] for r in records}):
        rows = [r for r in records if r["set"] == listed]
        pairs = sum(r["pairs"] for r in rows)
        out[listed] = {"pairs": pairs}
        for name in MEASURED:
            out[listed][name] = {
                key: sum(r[name][key] * r["pairs"] for r in rows) / pairs
                for key in ("inlier_ratio", "fmr", "kept_inlier_ratio", "kept_fmr")
            }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", help="a folder of 3DMatch scenes")
    parser.add_argument("--workdirs", default="runs", help="each fold trains in WORKDIRS/features-SCENE")
    parser.add_argument("--steps", type=int, default=None, help="steps per fold (default: the recipe's)")
    parser.add_argument("--record", default=None, help="also write the records to this file (JSON lines)")
    args = parser.parse_args()
    from dit_jax.training import descriptor_data

    stamp = {"benchmark": "descriptor_folds", "date": datetime.date.today().isoformat(), "cpus": os.cpu_count()}
    stamp["cpu"] = cpu_model()
    records = []
    for scene in descriptor_data.scene_names(args.scenes):
        result, seconds = run_fold(args.scenes, scene, os.path.join(args.workdirs, f"features-{scene}"), args.steps)
        for listed, learned in result["learned"].items():
            record = stamp | {"scene": scene, "set": listed, "pairs": learned["pairs"], "train_seconds": seconds}
            record |= {name: result[name][listed] for name in MEASURED}
            records.append(record)
            print(json.dumps(record), flush=True)
    total = stamp | {"scene": "all", "summed": summed(records)}
    print(json.dumps(total), flush=True)
    if args.record:
        with open(args.record, "w") as f:
            for record in [*records, total]:
                f.write(json.dumps(record) + "\n")
    print("\n| left out | list | pairs | FPFH | histograms | learned | learned / FPFH |\n|---|---|---|---|---|---|---|")
    for r in records:
        ratios = [r[name]["inlier_ratio"] for name in MEASURED]
        print(
            f"| {r['scene']} | {r['set']} | {r['pairs']} | "
            + " | ".join(f"{x:.3f}" for x in ratios)
            + f" | {ratios[2] / ratios[0]:.2f}x |"
        )


if __name__ == "__main__":
    main()
