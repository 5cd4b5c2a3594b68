"""Whole scenes placed by `dit_jax.scenes.scene.register_scene`, timed: the seconds per scan a user waits for.

    python benchmarks/register_scene.py --scenes ../shared/data/3dmatch          # each scene folder in turn
    python benchmarks/register_scene.py --scenes ../shared/data/3dmatch/hotel3   # one

Reads each 3DMatch scene folder's fragments (``cloud_bin_*``), loads the shipped weights once, and times
``register_scene`` on them (reading the files and loading the weights excluded; the first scene also pays for
compiling the estimator's programs where the cache is empty). Prints one line per scene, then one JSON
record: per scene the fragments, the pairs registered, the groups, the seconds and the seconds per fragment,
with the date and the CPU's model name. Whether the placement is right is evaluate.py's: `python evaluate.py
--scenes DIR`.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time

from dit_jax import io
from dit_jax.evaluators.scenes import scene_folders
from dit_jax.pipeline import registration
from dit_jax.scenes import scene
from dit_jax.training.precision import cpu_model


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", required=True, metavar="DIR", help="a 3DMatch scene folder, or a folder of them")
    return parser


def time_scene(registrar, folder) -> dict:
    """One scene's record: fragments, pairs registered, group sizes, seconds, seconds per fragment."""
    files = sorted(folder.glob("cloud_bin_*.*"), key=lambda f: int(f.stem.split("_")[-1]))
    clouds = [io.read(f) for f in files]
    started = time.perf_counter()
    built = scene.register_scene(registrar, clouds)
    seconds = time.perf_counter() - started
    return {
        "scene": folder.name,
        "fragments": len(clouds),
        "pairs": len(built.edges) + len(built.rejected),
        "groups": [len(c) for c in built.components],
        "seconds": round(seconds, 2),
        "seconds_per_fragment": round(seconds / len(clouds), 3),
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    registrar = registration.load()
    rows = []
    for folder in scene_folders(args.scenes):
        rows.append(time_scene(registrar, folder))
        row = rows[-1]
        print(f"{row['scene']}: {row['fragments']} fragments, {row['pairs']} pairs, {row['seconds']:.1f} s "
              f"({row['seconds_per_fragment']:.2f} s a fragment)")  # fmt: skip
    record = {
        "benchmark": "register_scene",
        "date": datetime.date.today().isoformat(),
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "scenes": rows,
    }
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
