"""A warm `register()` call on two real scans: where the time goes (sampling vs the network).

    python benchmarks/register_scans.py              # dragon scans 0 and 24 degrees (../shared)
    python benchmarks/register_scans.py --scans DIR --first a.ply --second b.ply

Loads the shipped weights, registers the pair once (compilation), then times --repeats warm calls (medians):
the whole `Registrar.register` and the network inside it (`Result.seconds`); the rest is sampling, input
checks, centring and transfers. Then the same with the float64 NumPy loop that sampled before (kept here only)
in place of the jitted farthest-point sampling. Prints a markdown table.
"""

import argparse
import datetime
import os
import statistics
import time

import numpy as np


def numpy_farthest_point_sample(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """The textbook farthest-point loop in NumPy float64 (same start, same indices as dit-jax's)."""
    rng = np.random.default_rng(seed)
    cloud = np.asarray(points, np.float64)
    chosen = np.empty(n, np.int64)
    chosen[0] = rng.integers(len(cloud))
    nearest = np.sum((cloud - cloud[chosen[0]]) ** 2, axis=1)
    for i in range(1, n):
        chosen[i] = np.argmax(nearest)
        np.minimum(nearest, np.sum((cloud - cloud[chosen[i]]) ** 2, axis=1), out=nearest)
    return chosen


def warm_calls(model, src, tgt, repeats: int) -> tuple[float, float]:
    """Medians of the whole call and of the network inside it (``Result.seconds``) over warm calls."""
    model.register(src, tgt, refine="none")  # compiles, or warms up; the network alone, as measured
    whole, network = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        result = model.register(src, tgt, refine="none")
        whole.append(time.perf_counter() - started)
        network.append(result.seconds)
    return statistics.median(whole), statistics.median(network)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", default="../shared/data/stanford_dragon_stand")
    parser.add_argument("--first", default="dragonStandRight_0.ply")
    parser.add_argument("--second", default="dragonStandRight_24.ply")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()

    from dit_jax import io, registration

    src = io.read(os.path.join(args.scans, args.first))
    tgt = io.read(os.path.join(args.scans, args.second))
    model = registration.load(verdict_rule="fitness")  # one direction, as measured before
    jitted = registration.farthest_point_sample
    rows = [("jitted (now)",) + warm_calls(model, src, tgt, args.repeats)]
    registration.farthest_point_sample = lambda points, n, seed=0, pool=None: numpy_farthest_point_sample(
        points, n, seed)  # the dragon scans are below the pool size, so no thinning either way
    try:
        rows.append(("NumPy float64 loop (before)",) + warm_calls(model, src, tgt, args.repeats))
    finally:
        registration.farthest_point_sample = jitted
    print(f"{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs; {args.first} ({len(src):,} points) onto "
          f"{args.second} ({len(tgt):,}); {model.settings.n_points} points per cloud; medians of {args.repeats} warm "
          f"calls\n")
    print("| farthest-point sampling | whole `register()` s | network s | rest (sampling, checks, transfers) s "
          "| whole / network |\n|---|---|---|---|---|")
    for name, whole, network in rows:
        print(f"| {name} | {whole:.3f} | {network:.3f} | {whole - network:.3f} | {whole / network:.2f} |")


if __name__ == "__main__":
    main()
