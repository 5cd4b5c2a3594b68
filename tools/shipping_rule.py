"""The shipping rule: whether a candidate's weights may replace the shipped ones.

    python tools/shipping_rule.py runs/stage/model --data-dir /data/modelnet40_ply_hdf5_1024 \
        --pairs 32 --out runs/stage/rule.json

Both checkpoints register the same held-out validation pairs (the training split's held-out shapes,
categories 0-19, :func:`dit_jax.training.validation_batches`; never a test pair) through the pipeline with
the shipped weights' inference settings and model options (:func:`inference_settings`), unrefined: what the
network and its GMCCE iterations give. The pairs
come twice: as the settings draw them from ModelNet40's points ("own"), and with every cloud resampled by a
sampler drawn per cloud (:data:`dit_jax.data.views.SAMPLERS`: uniform, a density gradient, farthest-point;
"varied"), so that a model that learned one sampling pattern is caught. The candidate passes where, on each
sampling, clean pairs lose nothing within 5 degrees, the :data:`HARD` settings together gain at least
:data:`GAIN` of a share within 5 degrees and none of them loses more than :data:`LOSS`.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from dit_jax import training
from dit_jax.data import views
from dit_jax.evaluators import common
from dit_jax.geometry import rigid
from dit_jax.pipeline import registration
from dit_jax.pipeline.settings import MODEL_OVERRIDES, InferenceSettings

#: The settings whose gains the rule sums.
HARD = ("high_noise_partial", "independent_clean", "independent_high_noise_partial", "scan_high_noise")
SETTINGS = ("clean", *HARD)
SAMPLINGS = ("own", "varied")
#: Summed share within ``common.RIGHT_DEG`` the hard settings must gain, and the most any one may lose.
GAIN, LOSS = 0.15, 0.1


def inference_settings(shipped: registration.Registrar) -> InferenceSettings:
    """The shipped weights' inference settings, unrefined, with every model option they run under (GMCCE
    threshold, kept share, guard, iterations, precision) written out: a checkpoint stores some of them in its
    model config, so without this a candidate exported from training would run its own (the authors'
    defaults) instead."""
    options = {name: getattr(shipped.config, name) for name in MODEL_OVERRIDES}
    return shipped.settings.replace(refine="none", rotation_search=False, **options)


def resampled(batch: dict, points: int, seed: int = 0) -> dict:
    """``batch`` with every cloud thinned to ``points`` (at most 80 % of its smallest cloud, so that every
    cloud is resampled) by a sampler drawn per cloud."""
    keep = min(points, int(0.8 * min(batch["src"].shape[1], batch["tgt"].shape[1])))
    rngs = [np.random.default_rng((seed, i)) for i in range(len(batch["src"]))]
    return views.thin(batch, keep, rngs, sampling="varied")


def errors_deg(registrar: registration.Registrar, batch: dict, bar=None) -> np.ndarray:
    """(P,) rotation errors (degrees) of the registrar's unrefined results on ``batch``'s pairs."""
    est = common.run_dit(registrar, list(zip(batch["src"], batch["tgt"])), bar=bar)[common.METHOD_DIT]
    return np.array([rigid.rotation_angle_deg(r.T @ t) for r, t in zip(est.rotation, batch["R"])])


def summary(errors: np.ndarray) -> dict:
    """Median and shares within 5 and 10 degrees of ``errors`` (P,)."""
    return {
        "median": float(np.median(errors)),
        "within_5": float(np.mean(errors <= common.RIGHT_DEG)),
        "within_10": float(np.mean(errors <= 10.0)),
    }


def verdict(shipped: dict, candidate: dict) -> dict:
    """The rule on ``{sampling: {setting: summary}}`` of both checkpoints: per sampling, the clean loss, the
    hard settings' summed gain and their largest loss, and whether the candidate passes on every sampling."""
    out = {}
    for sampling in shipped:
        gains = {s: candidate[sampling][s]["within_5"] - shipped[sampling][s]["within_5"] for s in HARD}
        clean_loss = shipped[sampling]["clean"]["within_5"] - candidate[sampling]["clean"]["within_5"]
        out[sampling] = {
            "clean_loss": clean_loss,
            "hard_gain": sum(gains.values()),
            "worst_hard_loss": max(0.0, -min(gains.values())),
            "passes": bool(clean_loss <= 0 and sum(gains.values()) >= GAIN and -min(gains.values()) <= LOSS),
        }
    out["ships"] = all(v["passes"] for v in out.values())
    return out


def table(results: dict) -> str:
    """Markdown: one row per checkpoint and sampling, median / within 5 / within 10 per setting."""
    lines = ["| checkpoint | sampling | " + " | ".join(SETTINGS) + " |", "|---" * (len(SETTINGS) + 2) + "|"]
    for name in ("shipped", "candidate"):
        for sampling, rows in results[name].items():
            cells = [
                f"{rows[s]['median']:.1f} / {rows[s]['within_5']:.2f} / {rows[s]['within_10']:.2f}" for s in SETTINGS
            ]
            lines.append(f"| {name} | {sampling} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python tools/shipping_rule.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("candidate", help="a model checkpoint (dit_jax.training.export_params)")
    parser.add_argument("--shipped", default=None, help="the weights to beat (default: the shipped ones)")
    parser.add_argument("--data-dir", required=True)
    parser.add_argument("--pairs", type=int, default=32, help="validation pairs per setting")
    parser.add_argument("--varied-points", type=int, default=384, help="points per cloud of the varied copy")
    parser.add_argument("--out", default=None, help="JSON with every figure and the verdict")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)

    shipped = registration.load(args.shipped)
    candidate = registration.load(args.candidate)
    settings = inference_settings(shipped)
    registrars = {
        "shipped": registration.Registrar(shipped.params, shipped.checkpoint_config, settings),
        "candidate": registration.Registrar(candidate.params, candidate.checkpoint_config, settings),
    }
    batches = training.validation_batches(args.data_dir, SETTINGS, count=args.pairs)
    copies = {"own": batches, "varied": {s: resampled(b, args.varied_points) for s, b in batches.items()}}
    bar = common.progress_bar(not args.no_progress, 2 * 2 * len(SETTINGS) * args.pairs, "register")
    results = {
        name: {
            sampling: {s: summary(errors_deg(reg, b, bar)) for s, b in copy.items()}
            for sampling, copy in copies.items()
        }
        for name, reg in registrars.items()
    }
    if bar is not None:
        bar.close()
    results["verdict"] = verdict(results["shipped"], results["candidate"])
    results.update(
        pairs=args.pairs, candidate_path=args.candidate, shipped_path=args.shipped or registration.shipped_weights()
    )
    print(table(results))
    print(json.dumps(results["verdict"], indent=1))
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
