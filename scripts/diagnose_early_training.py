"""Watch the first steps of a training run: loss terms, and on held-out pairs the network's temperature,
mean soft weight, match accuracy and rotation error.

    python scripts/diagnose_early_training.py --steps 60 --every 10 [--seed 0] [--set lr=3e-4] [--json out.json]

Uses ``python train.py``'s recipe (the ``quick`` preset; ``--set FIELD=VALUE`` changes TrainConfig fields),
without checkpoints. This is how the temperature stuck at its clamp was found (docs/BENCHMARKS.md, "Training
that learns on every seed").
"""

import argparse
import ast
import dataclasses
import json

import jax
import numpy as np

from dit_jax import losses, metrics, model, training
from dit_jax.data import pipeline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--every", type=int, default=10, help="steps between held-out probes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    parser.add_argument("--pairs", type=int, default=32, help="held-out pairs probed")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    changes = {k: ast.literal_eval(v) for k, v in (item.split("=", 1) for item in args.set)}
    config = dataclasses.replace(training.PRESETS["quick"], seed=args.seed, **changes)
    model_config = config.model_config()
    train_ds, val_ds = training.make_datasets(config)
    optimizer = training.make_optimizer(config, len(train_ds) // config.batch_size * config.epochs)
    mesh = training.make_mesh()
    state = training.replicate(training.init_state(config, optimizer), mesh)
    step = training.make_train_step(config, optimizer, mesh)

    @jax.jit
    def probe(params, src, tgt, rotation_gt, translation_gt):
        def one(s, t, r, tr):
            its = model.unroll(params, s, t, model_config, 1)
            labels = losses.match_labels(s, t, its.correspondences[0], r, tr)
            return (jax.numpy.mean(labels), its.temperature[0], jax.numpy.mean(its.soft_weights[0]),
                    metrics.rotation_error_deg(its.rotation[0], r))
        return jax.vmap(one)(src, tgt, rotation_gt, translation_gt)

    held_out = val_ds.batch(np.arange(min(args.pairs, len(val_ds))))

    def held_out_record(params) -> dict:
        values = probe(params, held_out["src"], held_out["tgt"], held_out["R"], held_out["t"])
        names = ("val_match_accuracy", "val_temperature", "val_soft_weight", "val_network_rotation_error")
        return {k: round(float(np.mean(v)), 5) for k, v in zip(names, values)}

    log = [dict(step=0, **held_out_record(state.params))]
    print(json.dumps(log[-1]), flush=True)
    n, epoch = 0, 0
    while n < args.steps:
        for batch in pipeline.batches(train_ds, config.batch_size, epoch=epoch):
            state, out = step(state, training.shard_batch(batch, mesh))
            n += 1
            record = {"step": n, **{k: round(float(v), 4) for k, v in jax.device_get(out).items()}}
            if n % args.every == 0:
                record.update(held_out_record(state.params))
            print(json.dumps(record), flush=True)
            log.append(record)
            if n >= args.steps:
                break
        epoch += 1
    if args.json:
        with open(args.json, "w") as f:
            json.dump(log, f)


if __name__ == "__main__":
    main()
