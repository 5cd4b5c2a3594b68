"""Killing ``dit-register --pairs`` at random moments and resuming: every pair gets one result, no record is lost.

    python benchmarks/kill_resume.py --pairs 30 --kills 20

A list of --pairs distinct pairs (copies of the README's chair pair, the network alone) goes through
``dit-register --pairs LIST --results R.jsonl``, killed with SIGKILL after a random delay (1 s to --longest)
--kills times and started again each time, then run to the end. After each start the file must begin with
every byte it held before (the log is never cut or rewritten). At the end each pair must have exactly one finished record. Then
the same list on a fresh file by two shard processes and a third that duplicates the first shard, at once,
killed once each midway and resumed: again one finished record per pair. Prints one JSON record; exit status 1
where an invariant fails.
"""

import argparse
import collections
import datetime
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

from dit_jax.training.precision import cpu_model

ROOT = pathlib.Path(__file__).resolve().parents[1]


def make_list(folder: pathlib.Path, count: int) -> pathlib.Path:
    """``count`` distinct pairs: copies of the example source, one target."""
    lines = []
    for k in range(count):
        copy = folder / f"src_{k}.ply"
        shutil.copyfile(ROOT / "examples" / "chair_src.ply", copy)
        lines.append(f"{copy} {ROOT / 'examples' / 'chair_tgt.pcd'}")
    listing = folder / "pairs.txt"
    listing.write_text("\n".join(lines) + "\n")
    return listing


def command(listing, results, checkpoint, *extra) -> list[str]:
    found = [sys.executable, "-m", "dit_jax.cli.register", "--pairs", str(listing), "--results", str(results)]
    found += ["--refine", "none", "--no-progress", "--no-verdict-status", *extra]
    return found + (["--checkpoint", str(checkpoint)] if checkpoint else [])


def finished_per_pair(results: pathlib.Path) -> collections.Counter:
    """How many finished records each pair index has; lines that do not parse are not records."""
    counts = collections.Counter()
    for line in results.read_bytes().split(b"\n"):
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if "level" in record and "error" not in record:
            counts[record["index"]] += 1
    return counts


def kill_and_resume(listing, results, checkpoint, kills: int, rng, longest: float) -> dict:
    """--kills runs killed after a random delay, each checked to keep what the file held; then one to the end."""
    lost, killed = 0, 0
    for _ in range(kills):
        before = results.read_bytes() if results.exists() else b""
        process = subprocess.Popen(command(listing, results, checkpoint), stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(1.0, longest))
        if process.poll() is None:
            process.send_signal(signal.SIGKILL)
            killed += 1
        process.wait()
        lost += not results.read_bytes().startswith(before)
    before = results.read_bytes()
    done = subprocess.run(command(listing, results, checkpoint), stderr=subprocess.PIPE, text=True)
    lost += not results.read_bytes().startswith(before)
    return {"killed": killed, "lost": lost, "final_status": done.returncode, "counts": finished_per_pair(results)}


def shards_at_once(listing, results, checkpoint, rng, longest: float) -> collections.Counter:
    """Two shards and a duplicate of the first at once, each killed once midway and started again."""
    shards = ("0/2", "1/2", "0/2")
    processes = [subprocess.Popen(command(listing, results, checkpoint, "--shard", s)) for s in shards]
    time.sleep(rng.uniform(longest / 2, longest))
    for process in processes:
        process.send_signal(signal.SIGKILL)
        process.wait()
    processes = [subprocess.Popen(command(listing, results, checkpoint, "--shard", s)) for s in shards]
    for process in processes:
        process.wait()
    return finished_per_pair(results)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=30)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--longest", type=float, default=8.0, help="the longest wait before a kill (seconds)")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as folder:
        folder = pathlib.Path(folder)
        listing = make_list(folder, args.pairs)
        started = time.perf_counter()
        killed = kill_and_resume(listing, folder / "killed.jsonl", args.checkpoint, args.kills, rng, args.longest)
        together = shards_at_once(listing, folder / "shared.jsonl", args.checkpoint, rng, args.longest)
    expected = {k: 1 for k in range(args.pairs)}
    record = {
        "benchmark": "kill_resume",
        "date": datetime.date.today().isoformat(),
        "cpu": cpu_model(),
        "pairs": args.pairs,
        "kills": killed["killed"],
        "runs_that_lost_bytes": killed["lost"],
        "one_record_per_pair_after_kills": dict(killed["counts"]) == expected,
        "final_status": killed["final_status"],
        "one_record_per_pair_with_three_writers": dict(together) == expected,
        "seconds": time.perf_counter() - started,
        "cpus": os.cpu_count(),
    }
    print(json.dumps(record))
    ok = (
        record["runs_that_lost_bytes"] == 0
        and record["one_record_per_pair_after_kills"]
        and record["one_record_per_pair_with_three_writers"]
        and record["final_status"] == 0
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
