"""Does the quick recipe learn on every seed? Trains it for each seed and variant, validates along the way.

    python benchmarks/seed_sweep.py --seeds 0-9 --variants clip_inward authors_clamp --json sweep.json
    python benchmarks/seed_sweep.py --seeds 0-4 --variants differentiable detached

Variants: ``clip_inward`` (dit-jax's temperature clamp, the default recipe), ``authors_clamp`` (the same with
``jnp.clip``, whose gradient is zero below 1/100), ``differentiable`` / ``detached`` (Procrustes with or
without gradients, with ``clip_inward``). Each run is ``python train.py``'s recipe (the ``quick`` preset,
embedded set, 308 steps) without checkpoints; one compiled step serves every seed of a variant. On a machine
without TFDS (a bare accelerator) the embedded set is read straight from its npz file. Set
``JAX_DEFAULT_MATMUL_PRECISION=highest`` on a GPU, where the default is TF32.
"""

import argparse
import dataclasses
import json
import os
import sys
import time


def _seeds(text: str) -> list[int]:
    if "-" in text:
        first, last = text.split("-")
        return list(range(int(first), int(last) + 1))
    return [int(s) for s in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-9", help="e.g. 0-9 or 0,3,5")
    parser.add_argument(
        "--variants",
        nargs="+",
        default=["clip_inward", "authors_clamp"],
        choices=["clip_inward", "authors_clamp", "differentiable", "detached"],
    )
    parser.add_argument("--steps", type=int, default=None, help="default: the quick preset's 308")
    parser.add_argument("--json", default=None, help="write every curve here")
    args = parser.parse_args()

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tools"))
    import packed

    no_tfds = packed.allow_without_tfds()
    import jax
    import jax.numpy as jnp
    import numpy as np

    from dit_jax import training
    from dit_jax.data import pairs, pipeline, shapes
    from dit_jax.network import head

    base = training.load_config("configs/quick.py")
    if no_tfds:  # the same shapes in the same order as the TFDS-prepared copy
        rows = list(shapes._read_embedded("train", base.n_points))
        all_shapes = shapes.Shapes(
            np.stack([r[1] for r in rows]),
            np.array([r[2] for r in rows]),
            np.array([r[0] for r in rows]),
            shapes._shape_names(shapes.EMBEDDED),
        )
    else:
        all_shapes = shapes.load_shapes(None, "train", n_points=base.n_points)
    train_shapes, val_shapes = training.split_validation(all_shapes, base.val_fraction)
    common = dict(setting=base.setting, variant=base.variant, n_points=base.n_points)
    val_ds = pairs.PairDataset(val_shapes, pairs.PairConfig(train=False, **common))
    steps_per_epoch = len(train_shapes.labels) // base.batch_size
    total = args.steps or steps_per_epoch * base.epochs
    optimizer = training.make_optimizer(base, total)
    mesh = training.make_mesh()
    model_config = base.model_config()
    checkpoints = sorted({0, 10, 20, 50, 100, 200, total})
    print(f"devices: {jax.devices()}; {total} steps; validation at {checkpoints}", flush=True)

    clip_inward = head.clip_inward
    authors_clamp = lambda x, lower, upper: jnp.clip(x, lower, upper)  # noqa: E731
    step_fns = {
        v: training.make_train_step(dataclasses.replace(base, differentiable=v != "detached"), optimizer, mesh)
        for v in args.variants
    }
    results = []
    for seed in _seeds(args.seeds):
        for variant in args.variants:
            # Read when the variant's step is first traced; later calls reuse that trace.
            head.clip_inward = authors_clamp if variant == "authors_clamp" else clip_inward
            config = dataclasses.replace(base, seed=seed)
            train_ds = pairs.PairDataset(train_shapes, pairs.PairConfig(train=True, seed=seed, **common))
            state = training.replicate(training.init_state(config, optimizer), mesh)
            curve = [dict(step=0, **training.validate(state.params, val_ds, model_config, base.val_pairs))]
            start, step, epoch = time.time(), 0, 0
            while step < total:
                for batch in pipeline.batches(train_ds, base.batch_size, epoch=epoch):
                    state, _ = step_fns[variant](state, training.shard_batch(batch, mesh))
                    step += 1
                    if step in checkpoints:
                        curve.append(
                            dict(step=step, **training.validate(state.params, val_ds, model_config, base.val_pairs))
                        )
                    if step >= total:
                        break
                epoch += 1
            results.append(dict(variant=variant, seed=seed, seconds=time.time() - start, curve=curve))
            print(
                json.dumps(
                    {
                        "variant": variant,
                        "seed": seed,
                        "network_rotation_error": [round(c["network_rotation_error"], 3) for c in curve],
                        "rotation_error": [round(c["rotation_error"], 5) for c in curve],
                        "network_match_accuracy": [round(c["network_match_accuracy"], 3) for c in curve],
                    }
                ),
                flush=True,
            )
            if args.json:
                with open(args.json, "w") as f:
                    json.dump(results, f)


if __name__ == "__main__":
    main()
