"""DIT+ICP on dense scans: time and error against the truth as the clouds grow to a million points.

    python benchmarks/dense_scans.py                      # dragon pairs 24 degrees apart (../shared)
    python benchmarks/dense_scans.py --pairs 3 --thicken 24 --target-points 25000 50000 100000 0

Real scanners give far more points than the Stanford Dragon's 42,000 a scan. Each scan is thickened to K
copies of itself, every point jittered by Gaussian noise of 0.1 % of the scan's extent (roughly, a denser scan
of the same surface), and the pairs are registered as users call it (`registration.load()`, `register(src,
tgt)`: the network, ICP, the verdict's second registration), warm (the first call compiles and is not
timed). Then, on the thickest clouds and ``--refine-pairs`` pairs, `icp_refine.refine` once from the network's own
estimate with the target thinned to each of ``--target-points`` (default: `icp.TARGET_POINTS`, as shipped,
and 0, the whole target).
Prints two markdown tables.
"""

import argparse
import datetime
import os
import statistics
import time

import numpy as np


def thicken(points: np.ndarray, copies: int, rng: np.random.Generator) -> np.ndarray:
    """(copies * N, 3): the points and copies - 1 jittered copies (noise 0.1 % of the extent)."""
    if copies == 1:
        return points
    sigma = 1e-3 * float(np.ptp(points, axis=0).max())
    return np.concatenate([points] + [points + rng.normal(scale=sigma, size=points.shape) for _ in range(copies - 1)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", default="../shared/data/stanford_dragon_stand")
    parser.add_argument("--pairs", type=int, default=5, help="the first N pairs of scans")
    parser.add_argument("--skip", type=int, default=1, help="pairs of scans this many apart (1: adjacent, 24 degrees)")
    parser.add_argument("--thicken", type=int, nargs="+", default=[1, 4, 24], help="copies of each scan")
    parser.add_argument(
        "--refine-pairs",
        type=int,
        default=3,
        help="pairs on which the thickest clouds are also refined alone at each --target-points",
    )
    parser.add_argument(
        "--target-points",
        type=int,
        nargs="+",
        default=None,
        help="targets thinned to this many points for the refinement alone (0: whole; "
        "default: icp.TARGET_POINTS and 0)",
    )
    args = parser.parse_args()

    from dit_jax.data import scans
    from dit_jax.geometry import icp, icp_refine, rigid
    from dit_jax.pipeline import registration

    pairs = scans.scan_pairs(scans.load_scans(args.scans), skip=args.skip)[: args.pairs]
    model = registration.load()
    network_only = registration.load(refine="none", verdict_rule="fitness")
    error = lambda rotation, pair: rigid.rotation_angle_deg(rotation @ pair.rotation.T)
    print(
        f"{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs; {len(pairs)} pairs of "
        f"{os.path.basename(os.path.normpath(args.scans))} scans, skip {args.skip}; "
        f"icp.TARGET_POINTS = {icp.TARGET_POINTS:,}\n"
    )
    print(
        "| points per scan | `register()` s per pair (median, max) | of which ICP | rotation error (deg), "
        "median / max | trusted |\n|---|---|---|---|---|"
    )
    thickest = {}
    for copies in args.thicken:
        rng = np.random.default_rng(copies)
        clouds = [(thicken(p.source, copies, rng), thicken(p.target, copies, rng)) for p in pairs]
        model.register(*clouds[0])  # compiles (per cloud size only the sampling differs; the network's shape not)
        seconds, icp_seconds, errors, trusted = [], [], [], 0
        for pair, (src, tgt) in zip(pairs, clouds):
            started = time.perf_counter()
            result = model.register(src, tgt)
            seconds.append(time.perf_counter() - started)
            icp_seconds.append(result.refine_seconds)
            errors.append(error(result.rotation, pair))
            trusted += bool(result.verdict)
        size = statistics.median(len(src) for src, _ in clouds)
        print(
            f"| {size:,.0f} | {statistics.median(seconds):.1f}, {max(seconds):.1f} | "
            f"{statistics.median(icp_seconds):.1f} | {statistics.median(errors):.3f} / {max(errors):.3f} | "
            f"{trusted} of {len(pairs)} |",
            flush=True,
        )
        thickest = {"copies": copies, "clouds": clouds}

    if not args.refine_pairs:
        return
    print(f"\n`icp_refine.refine`, one direction from the network's estimate, clouds of {thickest['copies']} copies:\n")
    print("| pair | target points | refine s | rotation error (deg) |\n|---|---|---|---|")
    caps = args.target_points if args.target_points is not None else [icp.TARGET_POINTS, 0]
    for pair, (src, tgt) in zip(pairs[: args.refine_pairs], thickest["clouds"]):
        estimate = network_only.register(src, tgt)
        scale = float(np.linalg.norm(src - src.mean(axis=0), axis=1).max())
        for cap in caps:
            started = time.perf_counter()
            refined = icp_refine.refine(
                src, tgt, estimate.rotation, estimate.translation, scale=scale, max_target_points=cap or None
            )
            label = (
                f"{len(tgt):,} (whole)"
                if not cap or cap >= len(tgt)
                else f"{cap:,}" + (" (shipped)" if cap == icp.TARGET_POINTS else "")
            )
            print(
                f"| {pair.name} | {label} | {time.perf_counter() - started:.1f} | "
                f"{error(refined.rotation, pair):.3f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
