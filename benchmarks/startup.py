"""Start-up time of `dit-register` with JAX's persistent compilation cache (dit_jax.compile_cache).

    python benchmarks/startup.py                     # the README's example pair
    python benchmarks/startup.py --src a.ply --tgt b.ply

Runs `dit-register --json` as a user would, each call a fresh process, and times it from the outside (wall
clock, interpreter start and imports included): once with the cache off, then twice with a new, empty cache
directory (the first call fills it, the second reads it). Each call's registration (network, refinement and
second candidate, as its JSON reports them) is subtracted to give its start-up: the interpreter, imports,
reading the files and the weights, sampling, and compilation or the cache's reads. Prints a markdown table.
"""

import argparse
import datetime
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]


def timed_call(args: list[str]) -> tuple[float, float]:
    """(wall seconds, the registration's own seconds) of one `dit-register --json` process."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "dit_jax.cli", *args, "--json"], cwd=ROOT, capture_output=True,
                          text=True)
    seconds = time.perf_counter() - started
    if done.returncode not in (0, 3):  # 3: a suspect verdict, still a full run
        raise SystemExit(f"dit-register failed: {done.stderr.strip()[-500:]}")
    report = json.loads(done.stdout)
    return seconds, report["seconds"] + report["refine_seconds"] + report["candidate_seconds"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--src", default="examples/chair_src.ply")
    parser.add_argument("--tgt", default="examples/chair_tgt.pcd")
    parser.add_argument("--refine", choices=("auto", "icp", "gicp", "none"), default=None,
                        help="dit-register's --refine (default: the shipped settings')")
    args = parser.parse_args()
    pair = [args.src, args.tgt] + (["--refine", args.refine] if args.refine else [])
    with tempfile.TemporaryDirectory() as cache:
        rows = [("cache off", timed_call(pair + ["--no-compile-cache"]))]
        rows.append(("first call, empty cache", timed_call(pair + ["--compile-cache", cache])))
        rows.append(("second call, cache filled", timed_call(pair + ["--compile-cache", cache])))
        size = sum(f.stat().st_size for f in pathlib.Path(cache).rglob("*") if f.is_file())
    print(f"{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, `dit-register {' '.join(pair)}`; "
          f"cache size {size / 2 ** 20:.1f} MB\n")
    print("| call | wall s | registration s | start-up s (the rest) |\n|---|---|---|---|")
    for name, (seconds, work) in rows:
        print(f"| {name} | {seconds:.2f} | {work:.2f} | {seconds - work:.2f} |")


if __name__ == "__main__":
    main()
