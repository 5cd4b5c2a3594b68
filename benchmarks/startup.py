"""Start-up time of `dit-register` with JAX's persistent compilation cache (dit_jax.compile_cache).

    python benchmarks/startup.py                     # the README's example pair
    python benchmarks/startup.py --src a.ply --tgt b.ply

Runs `dit-register` as a user would, each call a fresh process, and times it from the outside (wall clock,
interpreter start and imports included): once with the cache off, then twice with a new, empty cache
directory (the first call fills it, the second reads it). Prints a markdown table.
"""

import argparse
import datetime
import os
import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]


def timed_call(args: list[str]) -> float:
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "dit_jax.cli", *args], cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode not in (0, 3):  # 3: a suspect verdict, still a full run
        raise SystemExit(f"dit-register failed: {done.stderr.strip()[-500:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--src", default="examples/chair_src.ply")
    parser.add_argument("--tgt", default="examples/chair_tgt.pcd")
    parser.add_argument("--refine", choices=("none", "icp"), default="none",
                        help="dit-register's --refine (default none, as measured before ICP became its default: "
                             "ICP compiles nothing, so it adds the same seconds to every call)")
    args = parser.parse_args()
    pair = [args.src, args.tgt, "--refine", args.refine]
    with tempfile.TemporaryDirectory() as cache:
        rows = [("cache off", timed_call(pair + ["--no-compile-cache"]))]
        rows.append(("first call, empty cache", timed_call(pair + ["--compile-cache", cache])))
        rows.append(("second call, cache filled", timed_call(pair + ["--compile-cache", cache])))
        size = sum(f.stat().st_size for f in pathlib.Path(cache).rglob("*") if f.is_file())
    print(f"{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, `dit-register {' '.join(pair)}`; "
          f"cache size {size / 2 ** 20:.1f} MB\n")
    print("| call | wall s |\n|---|---|")
    for name, seconds in rows:
        print(f"| {name} | {seconds:.2f} |")


if __name__ == "__main__":
    main()
