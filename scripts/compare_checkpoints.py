"""Compares model checkpoints on validation pairs (training shapes, never test pairs): which one to go on with.

    python scripts/compare_checkpoints.py dit_jax/weights/dit-cpu-modelnet40 runs/a/model runs/b/model \
        --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --pairs 32

Every checkpoint registers the same validation pairs of each setting two ways: with the shipped weights'
inference setting, read from their checkpoint (three iterations, GMCCE threshold 0.9 keeping at least the 30 %
most consistent matches; guarded iterations since 2026-11-27: what `register` does) and as the network alone (one soft iteration, what training changes first). Prints a
markdown table of the median rotation error and the shares within 5 and 10 degrees.
"""

import argparse

import jax.numpy as jnp
import numpy as np

from dit_jax import checkpoint, metrics, model, registration, training

SETTINGS = ("clean", "high_noise_partial", "independent_clean", "independent_high_noise_partial", "scan_high_noise")
#: The inference options the shipped weights carry in their config (README, "Shipped weights").
INFERENCE_FIELDS = ("gmcce_threshold", "gmcce_min_keep", "guard_iterations")


def rotation_errors(params, config, batch, batch_size: int = 8) -> np.ndarray:
    """Isotropic rotation errors (P,) in degrees of ``config``'s registration of a validation batch."""
    errors = []
    for start in range(0, len(batch["src"]), batch_size):
        part = slice(start, start + batch_size)
        rotation, _, _ = model.register(params, jnp.asarray(batch["src"][part]), jnp.asarray(batch["tgt"][part]),
                                        config)
        errors.append(np.asarray(metrics.rotation_error_deg(rotation, jnp.asarray(batch["R"][part]))))
    return np.concatenate(errors)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=32, help="validation pairs per setting")
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS))
    args = parser.parse_args()

    shipped = checkpoint.read_config(registration.shipped_weights())
    shipped_inference = {name: getattr(shipped, name) for name in INFERENCE_FIELDS}
    batches = training.validation_batches(args.data_dir, args.settings, count=args.pairs, n_points=1000,
                                          unseen=args.unseen)
    print(f"{args.pairs} validation pairs per setting; median rotation error (deg) / within 5 / within 10\n")
    print("| checkpoint | mode | " + " | ".join(args.settings) + " |")
    print("|---|---|" + "---|" * len(args.settings))
    for path in args.checkpoints:
        params, config = checkpoint.restore(path)
        for mode, cfg in (("as shipped", config.replace(**shipped_inference)),
                          ("network alone", config.replace(n_iters=1))):
            cells = []
            for setting in args.settings:
                errors = rotation_errors(params, cfg, batches[setting])
                cells.append(f"{np.median(errors):.1f} / {np.mean(errors <= 5):.2f} / {np.mean(errors <= 10):.2f}")
            print(f"| {path} | {mode} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
