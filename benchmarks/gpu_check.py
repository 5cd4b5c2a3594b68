"""What a lent GPU says about dit-jax, in one command and one JSON record: correctness first, then speed.

    python benchmarks/gpu_check.py --reference ../shared/reference/dit_reference_a.npz --out runs/gpu_check
    python benchmarks/gpu_check.py --smoke --out runs/gpu_smoke        # the same parts, CPU-sized (the suite)

Parts, in this order (each is written to ``OUT/gpu_check.json`` as soon as it ends, so a lease that runs
out still leaves what was measured):

1. ``reference``: the reference check (``python -m dit_jax.network.reference_check``) at the default precision:
   checks passed of all, and the largest error as a share of its bound.
2. ``inference``: the paper's network (random weights: speed does not depend on them), ``model.register``
   at 1000 points, seconds per pair at batch 1 and 8 (median of the calls after a warm-up); then batch 1 at
   1000 and 4096 points with the device's peak bytes in use after each (the sizes run in increasing order,
   and the device's peak only grows) and XLA's estimate of each program's temporary buffers.
3. ``train_step``: the cpu and paper recipes' train step (``benchmarks/train_throughput.py``'s measure),
   seconds per step and pairs per second, in float32 and in bfloat16 (``TrainConfig.train_precision``; the
   two that ``train_precision="auto"`` chooses between), and the device's peak bytes in use after them.
4. ``training``: ``python train.py``'s loop on the quick recipe for 200 steps (no validation before the
   first step), its final validation.
5. ``estimator``: the rooms' global estimator (``dit_jax.features.compatibility.estimate``) on synthetic matches, 5 %
   of them right, at each padded size: seconds per call after its compilation, and whether the best motion is
   the true one; with ``--rooms DIR`` (the 3DMatch scenes) also one room pair registered by local features
   both ways (``dit_jax.features.matching.register_both_ways``), its seconds and rotation error.

Compiled programs go to the persistent cache (``--compile-cache``, default ``OUT/xla_cache``): carry it into
the next lease and the same shapes load instead of compiling. ``--smoke`` runs every part at sizes a CPU
does in about a minute (tiny network, 64 points, 2 training steps), to keep this script working; its
figures mean nothing. ``--only PART`` (repeatable) runs some parts. Exit status 1 where the reference check
fails, 0 otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import pathlib
import platform
import statistics
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # train_throughput.py, inference.py beside this script

PARTS = ("reference", "inference", "train_step", "training", "estimator")


@dataclasses.dataclass(frozen=True)
class Sizes:
    """What each part runs: the full check or the smoke test's stand-ins."""

    network: str  # a preset of dit_jax.network.configs for the inference part
    inference_points: int
    inference_batches: tuple[int, ...]
    memory_points: tuple[int, ...]
    repeats: int
    step_recipes: tuple[str, ...]
    step_points: int | None  # None: the recipe's own
    step_repeats: int
    training_recipe: str
    training_steps: int
    training_overrides: dict
    estimator_buckets: tuple[int, ...]


FULL = Sizes(
    network="paper",
    inference_points=1000,
    inference_batches=(1, 8),
    memory_points=(1000, 4096),
    repeats=5,
    step_recipes=("configs/cpu.py", "configs/paper.py"),
    step_points=None,
    step_repeats=5,
    training_recipe="configs/quick.py",
    training_steps=200,
    training_overrides={},
    estimator_buckets=(512, 1024, 2048),  # dit_jax.features.compatibility.BUCKETS
)
SMOKE = Sizes(
    network="tiny",
    inference_points=64,
    inference_batches=(1, 2),
    memory_points=(64, 96),
    repeats=1,
    step_recipes=("configs/tiny.py",),
    step_points=64,
    step_repeats=1,
    training_recipe="configs/quick.py",
    training_steps=2,
    training_overrides={"n_points": 64, "val_pairs": 4, "batch_size": 2, "model": "tiny"},
    estimator_buckets=(512,),
)


def device_peak_bytes() -> int | None:
    """The device's peak bytes in use so far (None on a CPU, which keeps no such count)."""
    import jax

    device = jax.devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    return stats.get("peak_bytes_in_use") if stats else None


def check_reference(path: str) -> dict:
    """The reference check's outcome at the default precision."""
    from dit_jax.network import reference_check

    with np.load(path) as npz:
        data = {k: npz[k] for k in npz.files}
    t0 = time.perf_counter()
    checks, unchecked = reference_check.compare(data, reference_check.compute(data))
    worst = max(checks, key=lambda c: c.value / c.bound if c.kind == "error" and c.bound else 0.0)
    return {
        "file": path,
        "passed": sum(c.passed for c in checks),
        "checks": len(checks),
        "failed": [c.name for c in checks if not c.passed],
        "worst_error": {"name": worst.name, "value": worst.value, "bound": worst.bound},
        "seconds": time.perf_counter() - t0,
    }


def time_inference(sizes: Sizes) -> dict:
    """Seconds per pair by batch, then peak memory by cloud size, of ``model.register``."""
    import jax

    from dit_jax.network import configs, model

    config = configs.get(sizes.network)
    params = model.init(jax.random.PRNGKey(0), config)
    rng = np.random.default_rng(0)

    def run(batch: int, n_points: int, repeats: int) -> dict:
        src = jax.device_put(rng.uniform(-1, 1, (batch, n_points, 3)).astype(np.float32))
        tgt = jax.device_put(src[:, ::-1] + 0.05)
        t0 = time.perf_counter()
        compiled = model.register.lower(params, src, tgt, config).compile()
        compile_s = time.perf_counter() - t0
        jax.block_until_ready(compiled(params, src, tgt))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(params, src, tgt))
            times.append(time.perf_counter() - t0)
        memory = compiled.memory_analysis()
        return {
            "batch": batch,
            "n_points": n_points,
            "compile_s": compile_s,
            "seconds_per_pair": statistics.median(times) / batch,
            "xla_temp_bytes": getattr(memory, "temp_size_in_bytes", None),
            "device_peak_bytes": device_peak_bytes(),
        }

    speed = [run(batch, sizes.inference_points, sizes.repeats) for batch in sizes.inference_batches]
    memory = [run(1, n, 1) for n in sizes.memory_points]
    return {"network": sizes.network, "n_iters": config.n_iters, "speed": speed, "memory": memory}


def time_train_steps(sizes: Sizes) -> list[dict]:
    """Each recipe's train step in float32 and in bfloat16."""
    from train_throughput import measure

    records = []
    for recipe in sizes.step_recipes:
        for precision in ("highest", "bfloat16"):
            record = measure(recipe, sizes.step_repeats, sizes.step_points, "preset", False, precision)
            records.append({**record, "device_peak_bytes": device_peak_bytes()})
    return records


def train_briefly(sizes: Sizes, workdir: str) -> dict:
    """The quick recipe's training loop for a few steps; its final validation."""
    from dit_jax import training
    from dit_jax.network import configs

    config = training.load_config(ROOT / sizes.training_recipe)
    overrides = dict(sizes.training_overrides)
    if "model" in overrides:
        overrides["model"] = configs.get(overrides["model"])
    # float32, as the README's figures were trained: the recipe's "auto" would spend the lease on timing both.
    overrides.setdefault("train_precision", None)
    config = dataclasses.replace(
        config, max_steps=sizes.training_steps, validate_at_start=False, eval_every=sizes.training_steps, **overrides
    )
    t0 = time.perf_counter()
    result = training.train(config, workdir, progress=False)
    seconds = time.perf_counter() - t0
    final = json.loads(json.dumps(result, default=str))  # the validation's metrics as plain numbers
    return {"recipe": sizes.training_recipe, "steps": sizes.training_steps, "seconds": seconds, **final}


def time_estimator(sizes: Sizes, rooms: str | None) -> dict:
    """The compatibility estimator per padded size on synthetic matches (5 % right), and one room pair."""
    import jax

    from dit_jax.data.pairs import euler_zyx_to_matrix
    from dit_jax.features import compatibility
    from dit_jax.geometry import rigid

    rng = np.random.default_rng(0)
    rotation, translation = euler_zyx_to_matrix([120.0, 40.0, -70.0]), np.array([3.0, -7.0, 1.5])
    buckets = []
    for size in sizes.estimator_buckets:
        src = rng.uniform(-5, 5, (size, 3))
        tgt = src @ rotation.T + translation
        wrong = rng.random(size) >= 0.05
        tgt[wrong] = rng.uniform(-5, 5, (wrong.sum(), 3)) @ rotation.T + translation
        args = (src.astype(np.float32), tgt.astype(np.float32), np.ones(size, bool), np.float32(0.05))
        t0 = time.perf_counter()
        jax.block_until_ready(compatibility.estimate(*args))
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(sizes.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compatibility.estimate(*args))
            times.append(time.perf_counter() - t0)
        found = compatibility.estimate_motions(src, tgt, 0.05)
        error = rigid.rotation_angle_deg(found.rotation[0].T @ rotation)
        buckets.append(
            {"matches": size, "compile_s": compile_s, "seconds": statistics.median(times), "error_deg": error}
        )
    record = {"buckets": buckets}
    if rooms:
        from dit_jax.data import scans
        from dit_jax.features import matching

        pair = scans.load_pair_sets(rooms)["3DMatch"].pairs[0]
        matching.register_both_ways(pair.source, pair.target)  # compiles
        t0 = time.perf_counter()
        estimate = matching.register_both_ways(pair.source, pair.target)
        record["room_pair"] = {
            "pair": pair.name,
            "seconds": time.perf_counter() - t0,
            "error_deg": rigid.rotation_angle_deg(estimate.kept[0].T @ pair.rotation),
        }
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for gpu_check.json, the training run and the cache")
    parser.add_argument("--reference", help="the authors' reference file (.npz); without it the part is skipped")
    parser.add_argument("--smoke", action="store_true", help="every part at CPU-sized stand-ins (see above)")
    parser.add_argument("--only", action="append", choices=PARTS, help="run this part (repeatable; default: all)")
    parser.add_argument("--compile-cache", help="persistent compilation cache (default: OUT/xla_cache)")
    parser.add_argument("--rooms", help="the 3DMatch scenes' folder: the estimator part also times a room pair")
    args = parser.parse_args(argv)

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from dit_jax.network import compile_cache

    compile_cache.enable(args.compile_cache or str(out / "xla_cache"))
    import jax

    sizes = SMOKE if args.smoke else FULL
    device = jax.devices()[0]
    record = {
        "date": datetime.date.today().isoformat(),
        "device": device.device_kind,
        "platform": device.platform,
        "host": platform.processor() or platform.machine(),
        "jax": jax.__version__,
        "smoke": args.smoke,
        "seconds": {},
    }
    path = out / "gpu_check.json"
    status = 0
    for part in args.only or PARTS:
        t0 = time.perf_counter()
        if part == "reference":
            if not args.reference:
                record[part] = "skipped: no --reference file"
            else:
                record[part] = check_reference(args.reference)
                status = 1 if record[part]["failed"] else status
        elif part == "inference":
            record[part] = time_inference(sizes)
        elif part == "train_step":
            record[part] = time_train_steps(sizes)
        elif part == "estimator":
            record[part] = time_estimator(sizes, args.rooms)
        elif part == "training":
            record[part] = train_briefly(sizes, str(out / "training"))
        record["seconds"][part] = time.perf_counter() - t0
        path.write_text(json.dumps(record, indent=2, default=float))
        print(f"gpu_check: {part} done in {record['seconds'][part]:.0f} s", file=sys.stderr, flush=True)
    print(json.dumps(record, indent=2, default=float))
    return status


if __name__ == "__main__":
    sys.exit(main())
