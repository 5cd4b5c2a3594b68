"""DIT's ICP refinement (`icp_refine.refine`): its time on scans and on small clouds, with one query thread and with
the default.

    python benchmarks/refine.py                  # dragon scans (../shared) and ModelNet40 validation pairs
    python benchmarks/refine.py --pairs 8 --data-dir ../shared/data/modelnet40_ply_hdf5_1024

One direction, from the shipped network's estimate (`register(..., refine="none")`), each pair refined with
``workers=1`` (one thread for the nearest-point queries) and with the default (the machine's cores, on targets
of at least `neighbours.PARALLEL_MIN_TARGET` points; smaller ones use small_gicp's tree in one thread either way);
prints the median seconds of each and whether every result is identical (it must be).
"""

import argparse
import datetime
import os
import statistics
import time

import numpy as np


def timed_refinements(pairs, registrar, modes) -> tuple[list[list[float]], bool]:
    """Seconds per pair of the refinement with each ``workers`` value in ``modes``, and whether all agree
    exactly. ``pairs``: (src (N, 3), tgt (M, 3)) tuples."""
    from dit_jax.geometry import icp_refine

    seconds, identical = [[] for _ in modes], True
    for src, tgt in pairs:
        estimate = registrar.register(src, tgt, refine="none")
        start = (np.asarray(estimate.rotation, np.float64), np.asarray(estimate.translation, np.float64))
        scale = float(max(np.linalg.norm(c - c.mean(0), axis=1).max() for c in (src, tgt)))
        results = []
        for workers, times in zip(modes, seconds):
            started = time.perf_counter()
            results.append(icp_refine.refine(src, tgt, *start, scale=scale, workers=workers))
            times.append(time.perf_counter() - started)
        a = results[0]
        identical &= all(
            np.array_equal(a.rotation, b.rotation)
            and np.array_equal(a.translation, b.translation)
            and a.iterations == b.iterations
            for b in results[1:]
        )
    return seconds, identical


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", default="../shared/data/stanford_dragon_stand")
    parser.add_argument("--scan-pairs", type=int, default=5, help="dragon pairs of each spacing (24, 48 degrees)")
    parser.add_argument(
        "--data-dir",
        default="../shared/data/modelnet40_ply_hdf5_1024",
        help="ModelNet40 (h5); validation pairs of categories 0-19",
    )
    parser.add_argument("--pairs", type=int, default=8, help="ModelNet40 validation pairs per setting")
    parser.add_argument("--settings", nargs="+", default=["high_noise_partial", "independent_clean", "scan_high_noise"])
    args = parser.parse_args()

    from dit_jax import training
    from dit_jax.data import scans as scans_lib
    from dit_jax.pipeline import registration

    registrar = registration.load(verdict_rule="fitness")  # the estimate only: one direction
    groups = {}
    if os.path.isdir(args.scans):
        scans = scans_lib.load_scans(args.scans)
        for skip in (1, 2):
            chosen = scans_lib.scan_pairs(scans, skip)[: args.scan_pairs]
            groups[f"dragon, {24 * skip}-degree pairs"] = [(p.source, p.target) for p in chosen]
    if os.path.isdir(args.data_dir):
        batches = training.validation_batches(args.data_dir, args.settings, count=args.pairs, unseen=True)
        for setting, b in batches.items():
            groups[f"ModelNet40 {setting}"] = [
                (b["src"][i].astype(np.float64), b["tgt"][i].astype(np.float64)) for i in range(len(b["src"]))
            ]
    if not groups:
        parser.error("neither --scans nor --data-dir exists")
    first = next(iter(groups.values()))[0]
    registrar.register(*first, refine="none")  # compiles

    modes = (1, None)
    print(
        f"`icp_refine.refine`, one direction, {os.cpu_count()} cores, {datetime.date.today().isoformat()}; "
        "median seconds per pair\n"
    )
    print("| pairs | count | one thread | default | identical |")
    print("|---|---|---|---|---|")
    for name, pairs in groups.items():
        seconds, identical = timed_refinements(pairs, registrar, modes)
        cells = " | ".join(f"{statistics.median(s):.2f}" for s in seconds)
        print(f"| {name} | {len(pairs)} | {cells} | {'yes' if identical else 'NO'} |", flush=True)


if __name__ == "__main__":
    main()
