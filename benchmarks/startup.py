"""Start-up time of `dit-register` with JAX's persistent compilation cache (dit_jax.compile_cache).

    python benchmarks/startup.py                     # the README's example pair
    python benchmarks/startup.py --src a.ply --tgt b.ply

Runs `dit-register --json` as a user would, each call a fresh process, and times it from the outside: once
with the cache off, then twice with a new, empty cache directory (the first call fills it, the second reads
it). Each call's wall time is split into its start-up (from launching the interpreter to the registration's
start: imports, reading the files and the weights), the registration (network, refinement and second
candidate, as its JSON reports them; the network's share includes compiling its program, or reading it from
the cache) and the rest (printing, and the interpreter's exit, where JAX shuts down). Prints a markdown table.
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


# Runs dit-register's main() as its console script does, and notes when main() starts and returns.
_WRAPPER = """
import contextlib, io, json, sys, time
started = time.time()
from dit_jax import cli
out = io.StringIO()
with contextlib.redirect_stdout(out):
    status = cli.main(sys.argv[1:])
print(json.dumps({"started": started, "returned": time.time(), "status": status, "report": out.getvalue()}))
"""


def timed_call(args: list[str]) -> tuple[float, float, float]:
    """(wall, start-up, registration) seconds of one `dit-register --json` process (see the module doc)."""
    launched = time.time()
    done = subprocess.run([sys.executable, "-c", _WRAPPER, *args, "--json"], cwd=ROOT, capture_output=True, text=True)
    ended = time.time()
    if done.returncode != 0:
        raise SystemExit(f"dit-register failed: {done.stderr.strip()[-500:]}")
    run = json.loads(done.stdout)
    if run["status"] not in (0, 3):  # 3: a suspect verdict, still a full run
        raise SystemExit(f"dit-register exited with {run['status']}: {done.stderr.strip()[-500:]}")
    report = json.loads(run["report"])
    work = report["seconds"] + report["refine_seconds"] + report["candidate_seconds"]
    return ended - launched, run["returned"] - launched - work, work


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--src", default="examples/chair_src.ply")
    parser.add_argument("--tgt", default="examples/chair_tgt.pcd")
    parser.add_argument(
        "--refine",
        choices=("auto", "icp", "gicp", "none"),
        default=None,
        help="dit-register's --refine (default: the shipped settings')",
    )
    args = parser.parse_args()
    pair = [args.src, args.tgt] + (["--refine", args.refine] if args.refine else [])
    with tempfile.TemporaryDirectory() as cache:
        rows = [("cache off", timed_call(pair + ["--no-compile-cache"]))]
        rows.append(("first call, empty cache", timed_call(pair + ["--compile-cache", cache])))
        rows.append(("second call, cache filled", timed_call(pair + ["--compile-cache", cache])))
        size = sum(f.stat().st_size for f in pathlib.Path(cache).rglob("*") if f.is_file())
    print(
        f"{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, `dit-register {' '.join(pair)}`; "
        f"cache size {size / 2**20:.1f} MB\n"
    )
    print("| call | wall s | start-up s | registration s | output and exit s |\n|---|---|---|---|---|")
    for name, (wall, startup, work) in rows:
        print(f"| {name} | {wall:.2f} | {startup:.2f} | {work:.2f} | {wall - startup - work:.2f} |")


if __name__ == "__main__":
    main()
