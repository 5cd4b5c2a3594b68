"""A warm `register()` call on two real scans: where the time goes (sampling vs the network).

    python benchmarks/register_scans.py              # dragon scans 0 and 24 degrees (../shared)
    python benchmarks/register_scans.py --scans DIR --first a.ply --second b.ply

Loads the shipped weights, registers the pair once (compilation), then times --repeats warm calls (median):
the whole `Registrar.register`, the network inside it (`Result.seconds`), and farthest-point sampling of
both clouds (`registration.farthest_point_sample`, jitted). For comparison it also times the float64 NumPy
loop that sampled before (kept here only). Prints a markdown table.
"""

import argparse
import datetime
import os
import statistics
import time

import numpy as np


def numpy_farthest_point_sample(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """The NumPy float64 loop dit-jax sampled with before 2026-11-26 (same start, same indices)."""
    rng = np.random.default_rng(seed)
    cloud = np.asarray(points, np.float64)
    chosen = np.empty(n, np.int64)
    chosen[0] = rng.integers(len(cloud))
    nearest = np.sum((cloud - cloud[chosen[0]]) ** 2, axis=1)
    for i in range(1, n):
        chosen[i] = np.argmax(nearest)
        np.minimum(nearest, np.sum((cloud - cloud[chosen[i]]) ** 2, axis=1), out=nearest)
    return chosen


def median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", default="../shared/data/stanford_dragon_stand")
    parser.add_argument("--first", default="dragonStandRight_0.ply")
    parser.add_argument("--second", default="dragonStandRight_24.ply")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    from dit_jax import io, registration

    src = io.read(os.path.join(args.scans, args.first))
    tgt = io.read(os.path.join(args.scans, args.second))
    model = registration.load()
    model.register(src, tgt)  # compiles
    results = [model.register(src, tgt) for _ in range(args.repeats)]
    whole = median_seconds(lambda: model.register(src, tgt), args.repeats)
    network = statistics.median(r.seconds for r in results)
    n = model.n_points

    def sample_both(sample):
        sample(src, n, seed=model.seed)
        sample(tgt, n, seed=model.seed + 1)

    fps = median_seconds(lambda: sample_both(registration.farthest_point_sample), args.repeats)
    numpy_fps = median_seconds(lambda: sample_both(numpy_farthest_point_sample), 1)
    print(f"{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs; {args.first} ({len(src):,} points) onto "
          f"{args.second} ({len(tgt):,}); {n} points per cloud; median of {args.repeats} warm calls\n")
    print("| part | s |\n|---|---|")
    print(f"| whole `register()` call | {whole:.3f} |")
    print(f"| the network (`Result.seconds`) | {network:.3f} |")
    print(f"| farthest-point sampling, both clouds (jitted) | {fps:.3f} |")
    print(f"| everything else (checks, centring, transfers, fitness) | {whole - network - fps:.3f} |")
    print(f"| (before: NumPy float64 sampling, both clouds) | {numpy_fps:.3f} |")
    print(f"\nwhole call / network = {whole / network:.2f}")


if __name__ == "__main__":
    main()
