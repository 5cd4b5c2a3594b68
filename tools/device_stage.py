"""One training stage on a lent GPU machine inside a fixed wall-clock budget, several runs side by side.

A development tool, not part of the package. Here, where the data is, pack the training shapes once (the
machine there has neither the data folder nor TFDS)::

    python tools/device_stage.py pack --data-dir $MODELNET40 --unseen \
        --out runs/device_data/mn40_train.npz

There (the device tool carries runs/device_data), from the repository root, either with ``--steps N`` or
with ``--seconds`` alone (then the recipe is timed first, at the cost of compiling it twice)::

    PYTHONPATH=. JAX_DEFAULT_MATMUL_PRECISION=highest python tools/device_stage.py run \
        --packed runs/device_data/mn40_train.npz --out $OUT --seconds 540 \
        --run corr --run nocorr:correspondence_weight=0.0 -- <train.py arguments shared by the runs>

``run`` first times the shared recipe for a few steps (which also compiles the validation into a shared
persistent cache), then chooses ``max_steps`` so that every run ends inside ``--seconds`` with its
learning-rate schedule whole, starts the runs side by side, stops any run still going at the deadline (its
best checkpoint so far is kept, or its latest where it never validated: ``--config.validate_at_start=False``
skips the validation before the first step, whose compiling ate most of a 15-minute lease), and writes to
``--out`` for each run one ``NAME.tar`` (``best/`` or ``checkpoints/``,
``metrics.jsonl``, ``train_config.json``: what ``python tools/ship_weights.py`` and
``dit_jax.training.export_params`` read) and a log, and ``xla_cache.tar``: the persistent compilation cache,
which the next lease carries back in (``--cache-from``) so that programs of the same shapes load instead of
compiling. Each run is ``python train.py``'s ``training.train``
with the given arguments; a recipe whose ``train_precision`` is "auto" is timed in both precisions by the
calibration alone, and the runs read its choice from the shared cache (with ``--steps``, which skips the
calibration, name the precision instead: runs side by side would time each other); the data are the packed shapes (``tools/packed.py``), recorded under the
directory they were packed from.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import subprocess
import sys
import tarfile
import time

#: The repository root: the tool runs from it (``python tools/device_stage.py``), where train.py is.
ROOT = os.getcwd()


def _use_packed(path: str) -> None:
    """Points dit_jax's shape loading at the packed file."""
    import packed

    packed.allow_without_tfds()
    from dit_jax.data import shapes as shapes_lib

    held = packed.load(path)
    shapes_lib.source_points = lambda source=None: held.points.shape[1]

    def load_shapes(source=None, split="train", n_points=1000, data_dir=None):
        if split != "train":
            raise shapes_lib.DataError(f"{path} holds the training split only")
        return shapes_lib.Shapes(held.points[:, :n_points], held.labels, held.ids, held.shape_names)

    shapes_lib.load_shapes = load_shapes


def worker(args) -> int:
    """One training run (a subprocess of ``run``)."""
    _use_packed(args.packed)
    import train as train_script
    from dit_jax import training
    from dit_jax.network import compile_cache

    compile_cache.enable(args.compile_cache)
    _, config, _ = train_script.parse(args.train_args)
    if config.init_from and config.init_from.startswith(ROOT + os.sep):
        # recorded relative to the repository, so the record still points at it on the machine that ships it
        config = dataclasses.replace(config, init_from=os.path.relpath(config.init_from, ROOT))
    import jax

    print(f"{args.workdir}: {jax.devices()} max_steps={config.max_steps}", flush=True)
    result = training.train(config, args.workdir, progress=False)
    print(json.dumps({k: v for k, v in result.items() if k != "val"}), flush=True)
    return 0


def _seconds_per_step(workdir: str) -> tuple[float, float]:
    """(steady seconds per step, seconds of the first logged interval, compilation included)."""
    records = [json.loads(line) for line in open(os.path.join(workdir, "metrics.jsonl"))]
    train = [r["seconds_per_step"] for r in records if r.get("split") == "train"]
    steady = sorted(train[1:] or train)
    return steady[len(steady) // 2], train[0]


def _launch(name: str, args, train_args: list[str], log_dir: str) -> subprocess.Popen:
    cmd = [
        sys.executable,
        os.path.abspath(__file__),
        "worker",
        "--packed",
        args.packed,
        "--compile-cache",
        args.compile_cache,
        "--workdir",
        os.path.join(args.workdir, name),
        "--",
        *train_args,
    ]
    log = open(os.path.join(log_dir, f"{name}.log"), "w")
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONUNBUFFERED="1")
    if args.autotune is not None:
        # XLA's GPU autotuning: at its default level the `cpu` recipe's train step did not compile in 170 s
        # on an H200; at level 0 it compiled in 65 s (docs/training.md, "The same stage on a lent GPU")
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_gpu_autotune_level={args.autotune}".strip()
    print(f"[{time.strftime('%H:%M:%S')}] {name}: {shlex.join(cmd)}", flush=True)
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT)


def _versions(*names: str) -> dict[str, str]:
    import importlib.metadata as md

    out = {}
    for name in names:
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = "missing"
    return out


def _bundle(workdir: str, out: str) -> None:
    """``best/`` (else, where no validation ran yet, ``checkpoints/``), the metrics and the config, as one tar:
    what :func:`dit_jax.training.export_params` reads."""
    best = os.path.join(workdir, "best")
    weights = "best" if os.path.isdir(best) and any(n.isdigit() for n in os.listdir(best)) else "checkpoints"
    with tarfile.open(out, "w") as tar:
        for name in (weights, "metrics.jsonl", "train_config.json"):
            if os.path.exists(os.path.join(workdir, name)):
                tar.add(os.path.join(workdir, name), arcname=name)


def _cache_in(tar_path: str, cache_dir: str) -> None:
    """Unpacks a compilation cache an earlier lease brought back (:func:`_cache_out`) into ``cache_dir``."""
    os.makedirs(cache_dir, exist_ok=True)
    with tarfile.open(tar_path) as tar:
        tar.extractall(cache_dir, filter="data")
    print(f"compilation cache: {len(os.listdir(cache_dir))} entries from {tar_path}", flush=True)


def _cache_out(cache_dir: str, out: str, limit: int = 8 << 20) -> None:
    """The compilation cache as one tar for the next lease (the programs of the same shapes then load in
    seconds instead of compiling): the largest entries first (the train steps), as many as fit in ``limit``
    bytes. The next lease carries it beside the packed shapes and the working tree, 64 MiB in all: 8 MiB holds
    the `cpu` recipe's two train steps and leaves that room."""
    if not os.path.isdir(cache_dir):
        return
    entries = sorted((e for e in os.scandir(cache_dir) if e.is_file()), key=lambda e: -e.stat().st_size)
    total = 0
    with tarfile.open(out, "w") as tar:
        for entry in entries:
            if total + entry.stat().st_size <= limit:
                tar.add(entry.path, arcname=entry.name)
                total += entry.stat().st_size
    print(f"compilation cache: {total / 2**20:.1f} MiB to {out}", flush=True)


def run(args) -> int:
    start = time.time()
    deadline = start + args.seconds
    print(_versions("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "chex", "numpy", "scipy"), flush=True)
    os.makedirs(args.out, exist_ok=True)
    os.makedirs(args.workdir, exist_ok=True)
    if args.cache_from:
        _cache_in(args.cache_from, args.compile_cache)
    runs = []
    for spec in args.run:
        name, _, sets = spec.partition(":")
        extra = [f"--config.{s}" for s in sets.split(",") if s]
        runs.append((name, extra))
    base = list(args.train_args)

    if args.steps:
        return _train_side_by_side(args, runs, base, start, deadline, args.steps, None)
    # Timing: the first run's recipe for a few steps, validation included (it fills the compile cache).
    calib = [
        *base,
        *runs[0][1],
        f"--config.max_steps={args.calibration_steps}",
        "--config.log_every=10",
        "--config.eval_every=1000000",
        "--config.ckpt_every=1000000",
    ]
    proc = _launch("calibration", args, calib, args.out)
    try:
        proc.wait(timeout=max(60.0, deadline - time.time() - 120))
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.returncode != 0:
        print(f"calibration failed ({proc.returncode}); the end of calibration.log:", flush=True)
        print(open(os.path.join(args.out, "calibration.log")).read()[-6000:], flush=True)
        return 1
    steady, first = _seconds_per_step(os.path.join(args.workdir, "calibration"))
    spent = time.time() - start
    # Side by side the runs share the GPU and the CPUs; compile again (a new schedule), validate --validations
    # times (and once at step 0 unless told not to).
    left = deadline - time.time() - args.margin
    per_step = steady * args.slowdown
    # the first logged interval holds one compilation; two more cloud sizes may follow in a mix
    compile_seconds = max(args.compile_seconds, 3 * 10 * first)
    steps = int((left - compile_seconds - (args.validations + 1) * args.validation_seconds) / per_step)
    steps = max(args.min_steps, steps // 50 * 50)
    print(
        f"calibration: {spent:.0f} s, {steady:.3f} s / step steady, {first:.2f} s / step in the first "
        f"interval; {left:.0f} s left, {compile_seconds:.0f} s for compiling -> {steps} steps",
        flush=True,
    )
    return _train_side_by_side(args, runs, base, start, deadline, steps, steady)


def _train_side_by_side(args, runs, base, start, deadline, steps, calibrated) -> int:
    every = max(10, steps // max(1, args.validations))
    ckpt_every = min(every, args.ckpt_every or every)
    procs = {}
    for name, extra in runs:
        procs[name] = _launch(
            name,
            args,
            [
                *base,
                *extra,
                f"--config.max_steps={steps}",
                f"--config.eval_every={every}",
                f"--config.ckpt_every={ckpt_every}",
            ],
            args.out,
        )
    for name, p in procs.items():
        try:
            p.wait(timeout=max(1.0, deadline - time.time() - args.margin / 2))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
            print(f"{name}: stopped at the deadline", flush=True)
    summary = {
        "seconds_per_step_calibration": calibrated,
        "steps": steps,
        "eval_every": every,
        "elapsed": round(time.time() - start),
        "runs": {},
    }
    for name, p in procs.items():
        workdir = os.path.join(args.workdir, name)
        summary["runs"][name] = {"returncode": p.returncode}
        if os.path.exists(os.path.join(workdir, "metrics.jsonl")):
            records = [json.loads(line) for line in open(os.path.join(workdir, "metrics.jsonl"))]
            summary["runs"][name]["last_step"] = max(r["step"] for r in records)
            summary["runs"][name]["last_val"] = [r for r in records if r.get("split") == "val"][-1:]
            _bundle(workdir, os.path.join(args.out, f"{name}.tar"))
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    _cache_out(args.compile_cache, os.path.join(args.out, "xla_cache.tar"))
    print(json.dumps(summary, indent=1), flush=True)
    return 0


def pack(args) -> int:
    import packed

    print(packed.pack(args.data_dir, args.out, labels=range(20) if args.unseen else None))
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="pack the training split here")
    p.add_argument("--data-dir", required=True)
    p.add_argument("--unseen", action="store_true", help="keep only categories 0-19")
    p.add_argument("--out", required=True)
    r = sub.add_parser("run", help="time, then train the runs side by side")
    r.add_argument("--packed", required=True)
    r.add_argument("--out", required=True, help="bundles and logs")
    r.add_argument("--workdir", default="/tmp/device_stage")
    r.add_argument("--compile-cache", default="/tmp/device_stage_xla")
    r.add_argument(
        "--cache-from",
        default=None,
        metavar="TAR",
        help="a compilation cache an earlier lease wrote to --out (xla_cache.tar), carried here",
    )
    r.add_argument("--seconds", type=float, required=True, help="wall-clock budget of the whole command")
    r.add_argument("--run", action="append", required=True, metavar="NAME[:FIELD=VALUE,...]")
    r.add_argument(
        "--steps",
        type=int,
        default=None,
        help="train this many steps, without timing the recipe first (each compile costs minutes)",
    )
    r.add_argument("--autotune", default="0", help="XLA's --xla_gpu_autotune_level for the runs (0: off)")
    r.add_argument("--calibration-steps", type=int, default=40)
    r.add_argument("--slowdown", type=float, default=1.3, help="step time side by side / alone (assumed)")
    r.add_argument(
        "--compile-seconds",
        type=float,
        default=60.0,
        help="at least this much, per run, in parallel (else 3 x the first logged interval)",
    )
    r.add_argument("--validation-seconds", type=float, default=8.0, help="assumed, once compiled")
    r.add_argument("--margin", type=float, default=40.0, help="seconds kept for stopping and bundling")
    r.add_argument("--min-steps", type=int, default=100)
    r.add_argument(
        "--validations",
        type=int,
        default=8,
        help="validations spread over each run, the end's included (1: the end's only; each setting's "
        "first validation compiles its registration, minutes on a fresh GPU machine)",
    )
    r.add_argument(
        "--ckpt-every",
        type=int,
        default=None,
        help="steps between checkpoints (default: the validations' interval); a run stopped at the "
        "deadline before any validation brings back its latest",
    )
    w = sub.add_parser("worker")
    w.add_argument("--packed", required=True)
    w.add_argument("--workdir", required=True)
    w.add_argument("--compile-cache", required=True)
    for s in (r, w):
        s.add_argument("train_args", nargs=argparse.REMAINDER, help="after --: train.py's arguments")
    args = parser.parse_args()
    if getattr(args, "train_args", None) and args.train_args[0] == "--":
        args.train_args = args.train_args[1:]
    return {"pack": pack, "run": run, "worker": worker}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
