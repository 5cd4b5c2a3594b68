"""Chooses a model's inference settings and its verdict threshold on validation pairs, never on test pairs.

    python scripts/choose_inference.py runs/mix/model --data-dir ../shared/data/modelnet40_ply_hdf5_1024 \
        --out runs/mix/inference_choice.json

Validation pairs are made from the training split's held-out shapes (the same ones training validates on,
categories 0-19 with ``--unseen``), for the authors' settings and those whose clouds share no point. Every
combination of GMCCE threshold, ``gmcce_min_keep`` and ``guard_iterations`` in the grid registers them; the
one with the most pairs within 5 degrees, averaged over the settings (ties: the lower mean log error), wins:
one setting for every input. The verdict threshold is then the lowest fitness at which at least 95 % of the
results it trusts are within 5 degrees, over all settings' pairs pooled.
"""

import argparse
import itertools
import json

import jax.numpy as jnp
import numpy as np

from dit_jax import checkpoint, metrics, model, training

SETTINGS = ("clean", "low_noise_partial", "high_noise_partial", "independent_clean", "scan_high_noise")
GRID = {"gmcce_threshold": (0.9, 0.0), "gmcce_min_keep": (0.0, 0.3), "guard_iterations": (False, True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=24, help="validation pairs per setting")
    parser.add_argument("--n-points", type=int, default=1000)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    params, config = checkpoint.restore(args.checkpoint)
    batches = training.validation_batches(args.data_dir, SETTINGS, count=args.pairs, n_points=args.n_points,
                                          unseen=args.unseen)

    variants = []
    for values in itertools.product(*GRID.values()):
        changes = dict(zip(GRID, values))
        if changes["gmcce_threshold"] == 0.0 and changes["gmcce_min_keep"] > 0:
            continue  # a zero threshold keeps every match already
        variants.append(changes)
    report = {"checkpoint": args.checkpoint, "settings": SETTINGS, "pairs_per_setting": args.pairs, "variants": []}
    for changes in variants:
        cfg = config.replace(**changes)
        row = {"changes": changes, "settings": {}}
        for setting, b in batches.items():
            errors, fitness = [], []
            for start in range(0, len(b["src"]), 8):
                sl = slice(start, start + 8)
                r, _, extras = model.register(params, jnp.asarray(b["src"][sl]), jnp.asarray(b["tgt"][sl]), cfg)
                errors.append(np.asarray(metrics.rotation_error_deg(r, jnp.asarray(b["R"][sl]))))
                fitness.append(np.asarray(extras["fitness"]))
            errors, fitness = np.concatenate(errors), np.concatenate(fitness)
            row["settings"][setting] = {"within_5": float(np.mean(errors <= 5)), "median": float(np.median(errors)),
                                        "mean_log": float(np.mean(np.log10(errors + 1e-6))),
                                        "errors": errors.tolist(), "fitness": fitness.tolist()}
        row["within_5"] = float(np.mean([s["within_5"] for s in row["settings"].values()]))
        row["mean_log"] = float(np.mean([s["mean_log"] for s in row["settings"].values()]))
        report["variants"].append(row)
        print(f"{json.dumps(changes)}: within 5 deg {row['within_5']:.3f} "
              + " ".join(f"{k}={v['within_5']:.2f}/{v['median']:.2f}" for k, v in row["settings"].items()), flush=True)
    best = max(report["variants"], key=lambda r: (r["within_5"], -r["mean_log"]))
    report["chosen"] = best["changes"]
    errors = np.concatenate([s["errors"] for s in best["settings"].values()])
    fitness = np.concatenate([s["fitness"] for s in best["settings"].values()])
    right = errors <= 5
    chosen_fitness = None
    for threshold in np.round(np.arange(0.0, 1.0001, 0.01), 2):
        trusted = fitness >= threshold
        if trusted.any() and right[trusted].mean() >= 0.95:
            chosen_fitness = float(threshold)
            break
    report["verdict_min_fitness"] = chosen_fitness
    if chosen_fitness is not None:
        trusted = fitness >= chosen_fitness
        report["verdict_on_validation"] = {
            "passed_right": float(right[trusted].mean()),
            "failures_caught": float((~trusted[~right]).mean()) if (~right).any() else None,
            "trusted": int(trusted.sum()), "pairs": int(len(errors))}
    print(f"chosen: {json.dumps(best['changes'])}; verdict threshold {chosen_fitness}; "
          f"{json.dumps(report.get('verdict_on_validation'))}")
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
