"""Data pipeline speed: preparing ModelNet40 through TFDS, and reading pairs against a training step.

    python benchmarks/data_throughput.py [--data-dir ../shared/data/modelnet40_ply_hdf5_1024]

Prints (1) the seconds to prepare the whole directory (both splits) into a fresh TFDS directory, (2) pairs per
second read by PairDataset.batch in batches of 8 for each setting, and (3) the seconds of one training step of
the smallest model (the `tiny` preset's network, batch 8, the same 1000-point pairs) and the ratio.
"""

import argparse
import dataclasses
import json
import pathlib
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--data-dir", default=str(ROOT.parent / "shared" / "data" / "modelnet40_ply_hdf5_1024"))
    parser.add_argument("--batch-size", type=int, default=8)
    args = parser.parse_args()

    from dit_jax import training
    from dit_jax.data import pairs, shapes

    out = {}
    with tempfile.TemporaryDirectory() as prepared:
        t0 = time.perf_counter()
        b = shapes.builder(args.data_dir, n_points=1000, data_dir=prepared)
        b.download_and_prepare()
        out["prepare_seconds"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        train = shapes.load_shapes(args.data_dir, "train", n_points=1000, data_dir=prepared)
        out["load_train_split_seconds"] = time.perf_counter() - t0

        bs = args.batch_size
        for setting in pairs.SETTINGS:
            ds = pairs.PairDataset(train, pairs.PairConfig(setting=setting, train=True))
            n_batches = 100
            t0 = time.perf_counter()
            for i in range(n_batches):
                ds.batch(np.arange(i * bs, (i + 1) * bs), epoch=0)
            out[f"pairs_per_second_{setting}"] = n_batches * bs / (time.perf_counter() - t0)

        config = dataclasses.replace(
            training.load_config("configs/tiny.py"), n_points=1000, batch_size=bs, data_dir=args.data_dir
        )
        optimizer = training.make_optimizer(config, 1000)
        mesh = training.make_mesh()
        state = training.replicate(training.init_state(config, optimizer), mesh)
        step = training.make_train_step(config, optimizer, mesh)
        ds = pairs.PairDataset(train, pairs.PairConfig(setting="clean", train=True))
        batch = training.shard_batch(ds.batch(np.arange(bs)), mesh)
        state, o = step(state, batch)
        o["loss"].block_until_ready()
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            state, o = step(state, batch)
            o["loss"].block_until_ready()
            times.append(time.perf_counter() - t0)
        out["tiny_train_step_seconds"] = float(np.median(times))
        read = bs / min(out[f"pairs_per_second_{s}"] for s in pairs.SETTINGS)
        out["read_batch_seconds_slowest_setting"] = read
        out["step_over_read_ratio"] = out["tiny_train_step_seconds"] / read
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
