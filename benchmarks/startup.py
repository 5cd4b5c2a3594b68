"""What a user waits for, from Python and from the shell, on one pair: start-up, loading, the first and later
registrations, with JAX's persistent compilation cache (dit_jax.network.compile_cache) empty and filled.

    python benchmarks/startup.py                     # the README's example pair
    python benchmarks/startup.py --src a.ply --tgt b.ply --repeats 5

Three parts, each call a fresh process:

* **Python API**: a session that imports JAX, imports ``dit_jax.pipeline.registration``, ``load()``s the shipped
  weights, reads the pair and registers it three times (the first call compiles or reads its programs from
  the cache), then once with ``refine="none"``; run with an empty cache (a machine's first-ever call), then
  twice more on it (the second of those is a warm cache's).
* **dit-register**: `dit-register --json`, timed from outside, with the cache off, then an empty one, then
  filled; each wall time split into start-up (launching the interpreter to the registration's start:
  imports, reading the files and the weights), the registration (as its JSON reports it) and the rest
  (printing, the interpreter's exit).
* **Beside Open3D**: the whole `dit-register` process on a warm cache and `benchmarks/open3d_pair.py` (the
  same pair by Open3D's FPFH, RANSAC and point-to-plane ICP), alternating, ``--repeats`` times each; medians.

Prints Markdown tables, then one JSON record of it all (with the CPU's model name).
"""

import argparse
import datetime
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

from dit_jax.training.precision import cpu_model

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Runs dit-register's main() as its console script does, and notes when main() starts and returns.
_WRAPPER = """
import contextlib, io, json, os, sys, time
started = time.time()
from dit_jax import cli
out = io.StringIO()
with contextlib.redirect_stdout(out):
    status = cli.main(sys.argv[1:])
print(json.dumps({"started": started, "returned": time.time(), "status": status, "report": out.getvalue()}), flush=True)
os._exit(0)  # as the console script leaves (dit_jax.cli.files.console_script)
"""

# A Python user's session, each step timed.
_SESSION = """
import json, sys, time
marks = [time.perf_counter()]
import jax
marks.append(time.perf_counter())
from dit_jax import io, registration
marks.append(time.perf_counter())
model = registration.load()
marks.append(time.perf_counter())
src, tgt = io.read(sys.argv[1]), io.read(sys.argv[2])
marks.append(time.perf_counter())
for _ in range(3):
    result = model.register(src, tgt)
    marks.append(time.perf_counter())
model.register(src, tgt, refine="none")
marks.append(time.perf_counter())
steps = ("import_jax", "import_registration", "load", "read", "first_register", "second_register",
         "third_register", "register_refine_none")
record = {name: round(b - a, 4) for name, a, b in zip(steps, marks, marks[1:])}
record["refine_s"] = round(result.refine_seconds, 4)
print(json.dumps(record))
"""


def _run(command: list[str], env: dict | None = None) -> tuple[float, str]:
    launched = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - launched
    if done.returncode not in (0, 3):  # 3: dit-register's suspect verdict, still a full run
        raise SystemExit(f"{' '.join(command[:3])} failed ({done.returncode}): {done.stderr.strip()[-500:]}")
    return wall, done.stdout


def api_session(pair: list[str], cache: str) -> dict:
    """One fresh Python process's :data:`_SESSION` with its cache at ``cache``."""
    env = dict(os.environ, DIT_JAX_COMPILE_CACHE=cache)
    wall, out = _run([sys.executable, "-c", _SESSION, *pair], env)
    return {**json.loads(out.splitlines()[-1]), "process_s": round(wall, 4)}


def cli_call(args: list[str]) -> dict:
    """(wall, start-up, registration) seconds of one `dit-register --json` process (see the module doc)."""
    launched = time.time()
    _, out = _run([sys.executable, "-c", _WRAPPER, *args, "--json"])
    ended = time.time()
    run = json.loads(out)
    report = json.loads(run["report"])
    work = report["seconds"] + report["refine_seconds"] + report["candidate_seconds"]
    return {"wall_s": ended - launched, "startup_s": run["returned"] - launched - work, "registration_s": work}


def side_by_side(pair: list[str], cache: str, repeats: int) -> dict:
    """Median wall seconds of the whole `dit-register` process (warm cache) and of the Open3D script,
    alternating."""
    dit = [os.path.join(os.path.dirname(sys.executable), "dit-register"), *pair, "--compile-cache", cache]
    o3d = [sys.executable, "benchmarks/open3d_pair.py", *pair]
    times: dict[str, list[float]] = {"dit_register_s": [], "open3d_script_s": []}
    _run(dit)  # fills whatever the cache still lacks for these settings
    for _ in range(repeats):
        times["dit_register_s"].append(_run(dit)[0])
        times["open3d_script_s"].append(_run(o3d)[0])
    medians = {name: statistics.median(values) for name, values in times.items()}
    return {**medians, "ratio": medians["dit_register_s"] / medians["open3d_script_s"], "all": times}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--src", default="examples/chair_src.ply")
    parser.add_argument("--tgt", default="examples/chair_tgt.pcd")
    parser.add_argument("--repeats", type=int, default=5, help="alternating runs of each side by side")
    args = parser.parse_args()
    pair = [args.src, args.tgt]
    with tempfile.TemporaryDirectory() as api_cache, tempfile.TemporaryDirectory() as cli_cache:
        sessions = [api_session(pair, api_cache) for _ in range(3)]
        calls = {"cache off": cli_call(pair + ["--no-compile-cache"])}
        calls["first call, empty cache"] = cli_call(pair + ["--compile-cache", cli_cache])
        calls["second call, cache filled"] = cli_call(pair + ["--compile-cache", cli_cache])
        beside = side_by_side(pair, cli_cache, args.repeats)
    record = {
        "benchmark": "startup",
        "date": datetime.date.today().isoformat(),
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "pair": pair,
        "api_empty_cache": sessions[0],
        "api_warm_cache": sessions[2],
        "dit_register": calls,
        "beside_open3d": beside,
    }
    print(f"{record['date']}, {record['cpus']} CPUs, {record['cpu']}; pair {' '.join(pair)}\n")
    print("| Python session (fresh process) | empty cache s | warm cache s |\n|---|---|---|")
    for step in ("import_jax", "import_registration", "load", "read", "first_register", "second_register",
                 "third_register", "register_refine_none", "refine_s", "process_s"):  # fmt: skip
        print(f"| {step} | {sessions[0][step]:.2f} | {sessions[2][step]:.2f} |")
    print("\n| `dit-register` call | wall s | start-up s | registration s | output and exit s |\n|---|---|---|---|---|")
    for name, c in calls.items():
        rest = c["wall_s"] - c["startup_s"] - c["registration_s"]
        print(f"| {name} | {c['wall_s']:.2f} | {c['startup_s']:.2f} | {c['registration_s']:.2f} | {rest:.2f} |")
    print(
        f"\nWhole process, warm cache, median of {args.repeats} alternating: dit-register "
        f"{beside['dit_register_s']:.2f} s, Open3D script {beside['open3d_script_s']:.2f} s ({beside['ratio']:.2f}x)\n"
    )
    print(json.dumps(record))


if __name__ == "__main__":
    main()
