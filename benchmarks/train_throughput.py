"""Training throughput (pairs per second) and peak memory of a preset's train step on this machine.

    python benchmarks/train_throughput.py --config configs/cpu.py
    python benchmarks/train_throughput.py --config configs/paper.py              # the authors' 1000 points, batch 2
    python benchmarks/train_throughput.py --config configs/paper.py --remat on   # blocks rematerialised

Random clouds of the preset's point count; the step is compiled first, then timed (median of --steps). Peak
memory: the process's peak resident set (VmHWM, compilation included) and, on an accelerator, the device's
peak bytes in use. Prints one JSON record.
"""

import argparse
import dataclasses
import datetime
import json
import time

import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/cpu.py", help="a recipe file")
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--n-points", type=int, default=None)
    parser.add_argument("--remat", choices=("preset", "on", "off"), default="preset",
                        help="rematerialised blocks (DITConfig.remat): the recipe's choice, or on / off")
    args = parser.parse_args()

    import jax

    from dit_jax import training
    from inference import peak_memory  # benchmarks/inference.py, beside this script

    config = training.load_config(args.config)
    if args.n_points:
        config = dataclasses.replace(config, n_points=args.n_points)
    if args.remat != "preset":
        config = dataclasses.replace(config, model=config.model.replace(remat=args.remat == "on"))
    optimizer = training.make_optimizer(config, 1000)
    mesh = training.make_mesh()
    state = training.replicate(training.init_state(config, optimizer), mesh)
    step = training.make_train_step(config, optimizer, mesh)
    rng = np.random.default_rng(0)
    b, n = config.batch_size, config.n_points
    src = rng.uniform(-1, 1, (b, n, 3)).astype(np.float32)
    batch = training.shard_batch({"src": src, "tgt": src[:, ::-1] + 0.1,
                                  "R": np.tile(np.eye(3, dtype=np.float32), (b, 1, 1)),
                                  "t": np.full((b, 3), 0.1, np.float32)}, mesh)
    t0 = time.perf_counter()
    state, out = step(state, batch)
    out["loss"].block_until_ready()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(args.steps):
        t0 = time.perf_counter()
        state, out = step(state, batch)
        out["loss"].block_until_ready()
        times.append(time.perf_counter() - t0)
    step_s = float(np.median(times))
    model_config = config.model_config()
    print(json.dumps({"date": datetime.date.today().isoformat(), "device": jax.devices()[0].device_kind,
                      "config": args.config, "n_points": n, "batch_size": b,
                      "train_iters": config.train_iters, "remat": model_config.remat,
                      "precision": model_config.precision, "compile_and_first_step_s": compile_s,
                      "step_s": step_s, "pairs_per_s": b / step_s, **peak_memory()}, indent=2))


if __name__ == "__main__":
    main()
