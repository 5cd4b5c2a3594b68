"""The two refinements of DIT's estimate side by side on real scans: `icp.refine` (``refine="icp"``) and
`icp.refine_gicp` (``refine="gicp"``, small_gicp's generalized ICP at the clouds' point spacing).

    python benchmarks/refine_methods.py ../shared/data/stanford_dragon_stand ../shared/data/3dmatch_redkitchen \\
        ../shared/data/lidar_pair

Each folder is read as `evaluate.py --scans` reads it (`dit_jax.data.scans.load_pair_sets`; a series gives
adjacent scans, ``--skips``). One direction, from the shipped network's own estimate (``refine="none"``, the
fitness verdict), each pair is refined by both; per pair set it prints the pairs within 1 and 5 degrees and
registered by the set's benchmark criterion, the median rotation error and the mean seconds of the
refinement, for the network alone and each refinement. The last line is one JSON record of it all.
"""

import argparse
import datetime
import json
import os
import time

import numpy as np

from dit_jax import icp, registration
from dit_jax.data import scans
from dit_jax.geometry import rotation_angle_deg

METHODS = {
    "icp": lambda src, tgt, r, t, scale: icp.refine(src, tgt, r, t, scale=scale),
    "gicp": lambda src, tgt, r, t, scale: icp.refine_gicp(src, tgt, r, t),
}


def measure(folders, skips=(1,)) -> dict:
    registrar = registration.load(refine="none", verdict_rule="fitness")
    out = {}
    for folder in folders:
        for set_name, found in scans.load_pair_sets(folder, skips).items():
            rows = []
            for pair in found.pairs:
                estimate = registrar.register(pair.source, pair.target)
                scale = float(max(np.linalg.norm(c - c.mean(0), axis=1).max() for c in (pair.source, pair.target)))
                row = {"pair": pair.name, "network": _errors(pair, estimate.rotation, estimate.translation, 0.0)}
                for name, method in METHODS.items():
                    started = time.perf_counter()
                    refined = method(pair.source, pair.target, estimate.rotation, estimate.translation, scale)
                    row[name] = _errors(pair, refined.rotation, refined.translation, time.perf_counter() - started)
                rows.append(row)
            key = f"{os.path.basename(os.path.normpath(folder))}/{set_name}"
            out[key] = {
                "criterion": found.criterion,
                "rows": rows,
                "summary": {m: _summary([r[m] for r in rows], found.criterion) for m in ("network", *METHODS)},
            }
    return out


def _errors(pair, rotation, translation, seconds) -> dict:
    return {
        "rot_err": rotation_angle_deg(np.asarray(rotation).T @ pair.rotation),
        "trans_err": float(np.linalg.norm(np.asarray(translation) - pair.translation)),
        "seconds": seconds,
    }


def _summary(rows, criterion) -> dict:
    rot = np.array([r["rot_err"] for r in rows])
    out = {
        "pairs": len(rows),
        "within_1": int((rot <= 1).sum()),
        "within_5": int((rot <= 5).sum()),
        "rot_median": float(np.median(rot)),
        "seconds": float(np.mean([r["seconds"] for r in rows])),
    }
    if criterion:
        out["registered"] = int(sum(r["rot_err"] <= criterion[0] and r["trans_err"] <= criterion[1] for r in rows))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+")
    parser.add_argument("--skips", nargs="+", type=int, default=[1])
    args = parser.parse_args(argv)
    results = measure(args.folders, tuple(args.skips))
    print(
        f"refinements from the network's estimate, one direction, {os.cpu_count()} cores, "
        f"{datetime.date.today().isoformat()}\n"
    )
    print(
        "| pair set | method | pairs | within 1 deg | within 5 deg | registered | median rotation error (deg) "
        "| s / pair |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for key, r in results.items():
        for method, s in r["summary"].items():
            registered = f"{s['registered']}" if "registered" in s else "-"
            print(
                f"| {key} | {method} | {s['pairs']} | {s['within_1']} | {s['within_5']} | {registered} | "
                f"{s['rot_median']:.2f} | {s['seconds']:.2f} |"
            )
    print(
        json.dumps(
            {
                "benchmark": "refine_methods",
                "date": datetime.date.today().isoformat(),
                "cores": os.cpu_count(),
                "results": {k: {"criterion": v["criterion"], "summary": v["summary"]} for k, v in results.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
