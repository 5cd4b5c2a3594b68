"""Calibration: a checkpoint's inference settings and verdict thresholds, chosen on validation pairs (never
test pairs) through the registration pipeline, and recorded in the checkpoint's
:class:`~dit_jax.pipeline.settings.InferenceSettings`.

    python tools/calibrate.py runs/mix/model --data-dir /data/modelnet40_ply_hdf5_1024 --unseen --out choice.json
    python tools/calibrate.py dit_jax/network/weights/dit-cpu-modelnet40 --verdict-only --record --data-dir ... --pairs 128 --out v.json
    python tools/calibrate.py dit_jax/network/weights/dit-cpu-modelnet40 --rechoose v.json --record --out v2.json

Validation pairs come from the training split's held-out shapes (the ones training validates on). Every
combination of the GMCCE grid (:data:`GRID`, and ``--iters``) registers them, the network alone; the one
with most pairs within 5 degrees averaged over the settings (ties: the lower mean log error) wins, one setting
for every input. The fitness verdict's threshold is then the lowest fitness at which at least
:data:`PRECISION` of the results it trusts are right (within ``common.RIGHT_DEG``, 5 degrees).

The agreement verdict: each pair runs the whole pipeline (both directions, refined by ICP as users get it),
and each refinement's threshold is the largest of :data:`AGREEMENT_GRID` at which at least
:data:`PRECISION` of the results it trusts are right, pooled over the settings whose clouds
share no point (``--verdict-pool independent``: users' data never shares points). Where none reaches it, the
most precise threshold is taken (:func:`fallback_threshold`) and named in ``verdict_fallback``. The bands of
agreement and how often each was right go into the settings too, quoted beside every verdict.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os

import numpy as np

from dit_jax import training
from dit_jax.data import pairs as pairs_lib
from dit_jax.evaluators import common
from dit_jax.geometry import rigid
from dit_jax.network import checkpoint
from dit_jax.pipeline import registration
from dit_jax.pipeline import settings as settings_lib
from dit_jax.pipeline.settings import REFINEMENTS, InferenceSettings
from dit_jax.pipeline.verdict import MIN_BAND_PAIRS

#: The settings the inference options are chosen on.
SETTINGS = ("clean", "low_noise_partial", "high_noise_partial", "independent_clean", "scan_high_noise")
#: Candidate thresholds (degrees) of the agreement verdict.
AGREEMENT_GRID = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
#: A verdict threshold must leave at least this share of the results it trusts right (``common.RIGHT_DEG``).
PRECISION = 0.95
#: The GMCCE options searched (with ``--iters``, the iteration count too).
GRID = {"gmcce_threshold": (0.9, 0.0), "gmcce_min_keep": (0.0, 0.3), "guard_iterations": (False, True)}


def largest_threshold(errors: np.ndarray, agreement: np.ndarray) -> float | None:
    """The largest :data:`AGREEMENT_GRID` value at which at least :data:`PRECISION` of the results with
    ``agreement`` (P,) at or below it have ``errors`` (P,) within ``common.RIGHT_DEG``; None if none does."""
    chosen = None
    for threshold in AGREEMENT_GRID:
        trusted = agreement <= threshold
        if trusted.any() and np.mean(errors[trusted] <= common.RIGHT_DEG) >= PRECISION:
            chosen = threshold
    return chosen


def fallback_threshold(curve: list[dict]) -> float:
    """The :data:`AGREEMENT_GRID` threshold whose trusted results are most often right on ``curve`` (one
    :func:`dit_jax.evaluators.common.verdict_summary` per grid value), the smaller on a tie. One that trusts
    none counts as always right; one that trusts fewer than :data:`dit_jax.pipeline.verdict.MIN_BAND_PAIRS` is not
    taken (too few to say how often they are right), unless every threshold is such, when the smallest is."""
    candidates = [
        (1.0 if row["passed"] == 0 else row["passed_right"], -t)
        for t, row in zip(AGREEMENT_GRID, curve)
        if row["passed"] == 0 or row["passed"] >= MIN_BAND_PAIRS
    ]
    return -max(candidates)[1] if candidates else AGREEMENT_GRID[0]


def gather_agreement(registrar: registration.Registrar, batches: dict) -> dict:
    """Each validation pair of ``batches`` ({setting: batch}) through the pipeline as users run it: per
    refinement ("none": the network's result, "icp": the refined one), ``{"setting", "rot_err",
    "agreement"}``, each a list over all pairs."""
    per_pair = {refine: {"setting": [], "rot_err": [], "agreement": []} for refine in REFINEMENTS}
    agreement_registrar = registrar.replace(verdict_rule="agreement", refine="icp")
    for setting, b in batches.items():
        found = common.run_dit(agreement_registrar, list(zip(b["src"], b["tgt"])))
        for refine, method in (("none", common.METHOD_DIT), ("icp", common.METHOD_DIT_ICP)):
            est = found[method]
            errors = [rigid.rotation_angle_deg(r.T @ t) for r, t in zip(est.rotation, b["R"])]
            per_pair[refine]["setting"] += [setting] * len(errors)
            per_pair[refine]["rot_err"] += np.round(errors, 5).tolist()
            per_pair[refine]["agreement"] += np.round(est.agreement, 5).tolist()
        print(f"{setting}: agreement gathered", flush=True)
    return per_pair


def choose_from_evidence(per_pair: dict, pooled: list[str]) -> dict:
    """The agreement thresholds per refinement from gathered evidence (:func:`gather_agreement`), chosen over
    the settings ``pooled``, with the precision curve, the bands and the figures per setting."""
    report = {
        "verdict_max_disagreement": {},
        "verdict_pool": list(pooled),
        "verdict_agreement_on_validation": {},
        "verdict_curve": {},
        "verdict_agreement_bands": {},
        "per_pair": per_pair,
        "verdict_fallback": [],
    }
    for refinement, evidence in per_pair.items():
        errors, agreement = np.asarray(evidence["rot_err"], float), np.asarray(evidence["agreement"], float)
        settings = np.asarray(evidence["setting"])
        in_pool = np.isin(settings, pooled)
        report["verdict_curve"][refinement] = curve = [
            common.verdict_summary(errors[in_pool], agreement[in_pool] <= t, common.agreement_rule(t), common.RIGHT_DEG)
            for t in AGREEMENT_GRID
        ]
        report["verdict_agreement_bands"][refinement] = common.agreement_bands(
            errors[in_pool], agreement[in_pool], AGREEMENT_GRID, common.RIGHT_DEG
        )
        threshold = largest_threshold(errors[in_pool], agreement[in_pool])
        if threshold is None:
            threshold = fallback_threshold(curve)
            report["verdict_fallback"].append(refinement)
        report["verdict_max_disagreement"][refinement] = threshold
        rule = common.agreement_rule(threshold)
        report["verdict_agreement_on_validation"][refinement] = {
            "pooled": common.verdict_summary(errors, agreement <= threshold, rule, common.RIGHT_DEG),
            "pool": common.verdict_summary(errors[in_pool], agreement[in_pool] <= threshold, rule, common.RIGHT_DEG),
            **{
                s: common.verdict_summary(
                    errors[settings == s], agreement[settings == s] <= threshold, rule, common.RIGHT_DEG
                )
                for s in dict.fromkeys(settings.tolist())
            },
        }
        print(
            f"refine={refinement}: agreement within {threshold:g} deg"
            + (" (fallback)" if refinement in report["verdict_fallback"] else ""),
            flush=True,
        )
    return report


def choose_inference(registrar: registration.Registrar, batches: dict, grid: dict) -> dict:
    """The GMCCE options (and iteration count) of ``grid`` that register most validation pairs within 5
    degrees, the network alone, with the fitness verdict's threshold for them."""
    variants = []
    for values in itertools.product(*grid.values()):
        changes = dict(zip(grid, values))
        if changes.get("gmcce_threshold") == 0.0 and changes.get("gmcce_min_keep", 0) > 0:
            continue  # a zero threshold keeps every match already
        variants.append(changes)
    report = {"grid": {k: list(v) for k, v in grid.items()}, "variants": []}
    for changes in variants:
        run = registrar.replace(refine="none", verdict_rule="fitness", **changes)
        row = {"changes": changes, "settings": {}}
        for setting, b in batches.items():
            est = common.run_dit(run, list(zip(b["src"], b["tgt"])))[common.METHOD_DIT]
            errors = np.array([rigid.rotation_angle_deg(r.T @ t) for r, t in zip(est.rotation, b["R"])])
            row["settings"][setting] = {
                "within_5": float(np.mean(errors <= 5)),
                "median": float(np.median(errors)),
                "mean_log": float(np.mean(np.log10(errors + 1e-6))),
                "errors": errors.tolist(),
                "fitness": est.fitness.tolist(),
            }
        row["within_5"] = float(np.mean([s["within_5"] for s in row["settings"].values()]))
        row["mean_log"] = float(np.mean([s["mean_log"] for s in row["settings"].values()]))
        report["variants"].append(row)
        print(f"{json.dumps(changes)}: within 5 deg {row['within_5']:.3f}", flush=True)
    best = max(report["variants"], key=lambda r: (r["within_5"], -r["mean_log"]))
    report["chosen"] = best["changes"]
    errors = np.concatenate([s["errors"] for s in best["settings"].values()])
    fitness = np.concatenate([s["fitness"] for s in best["settings"].values()])
    right = errors <= common.RIGHT_DEG
    report["verdict_min_fitness"] = next(
        (
            float(t)
            for t in np.round(np.arange(0.0, 1.0001, 0.01), 2)
            if (fitness >= t).any() and right[fitness >= t].mean() >= PRECISION
        ),
        None,
    )
    return report


def record(path: str, report: dict) -> InferenceSettings:
    """Writes a choice into the checkpoint's inference settings (its params untouched), with the evidence it
    rests on under ``calibration``. Returns the new settings."""
    extra = checkpoint.read_extra(path)
    settings = registration.settings_from_extra(extra)
    changes = {}
    if "verdict_max_disagreement" in report:
        thresholds, bands = report["verdict_max_disagreement"], report.get("verdict_agreement_bands", {})
        changes.update(
            max_disagreement_network=thresholds.get("none", settings.max_disagreement_network),
            max_disagreement_icp=thresholds.get("icp", settings.max_disagreement_icp),
            agreement_bands_network=bands.get("none"),
            agreement_bands_icp=bands.get("icp"),
        )
    if "chosen" in report:
        changes.update(report["chosen"])
        if report.get("verdict_min_fitness") is not None:
            changes["min_fitness"] = report["verdict_min_fitness"]
    settings = settings.replace(**changes)
    evidence = {k: v for k, v in report.items() if k not in ("per_pair", "variants")}
    checkpoint.update_extra(path, {registration.SETTINGS_KEY: settings.to_dict(), "calibration": evidence})
    print(f"recorded in {path}: {json.dumps({k: v for k, v in changes.items() if 'bands' not in k})}")
    return settings


def _pooled(settings, pool: str) -> list[str]:
    return [s for s in settings if pool == "all" or pairs_lib.SETTINGS[s].independent] or list(settings)


def build_parser() -> argparse.ArgumentParser:
    """calibrate's command line."""
    parser = argparse.ArgumentParser(prog="python tools/calibrate.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=24, help="validation pairs per setting")
    parser.add_argument("--out", required=True, help="where the choice and its evidence go (JSON)")
    parser.add_argument(
        "--verdict-settings",
        nargs="+",
        default=list(pairs_lib.SETTINGS),
        help="settings the agreement verdict is chosen on (default: all)",
    )
    parser.add_argument(
        "--verdict-pool",
        choices=("independent", "all"),
        default="independent",
        help="settings the thresholds are chosen over: those whose clouds share no point, or all",
    )
    parser.add_argument("--verdict-only", action="store_true", help="choose the agreement thresholds only")
    parser.add_argument(
        "--rechoose",
        default=None,
        metavar="JSON",
        help="choose the thresholds again from the evidence an earlier --out kept",
    )
    settings_lib.add_flags(parser, ("iters",), grid=True)
    parser.add_argument("--keep-gmcce", action="store_true", help="search only --iters")
    parser.add_argument("--record", action="store_true", help="write the choice into the checkpoint")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    if args.rechoose:
        with open(args.rechoose) as f:
            earlier = json.load(f)
        if os.path.realpath(earlier.get("checkpoint", args.checkpoint)) != os.path.realpath(args.checkpoint):
            parser.error(f"{args.rechoose} holds the evidence of {earlier['checkpoint']}, not {args.checkpoint}")
        settings = list(dict.fromkeys(earlier["per_pair"]["icp"]["setting"]))
        report = {
            "checkpoint": args.checkpoint,
            "rechosen_from": args.rechoose,
            **choose_from_evidence(earlier["per_pair"], _pooled(settings, args.verdict_pool)),
        }
    else:
        registrar = registration.load(args.checkpoint)
        n_points = registrar.settings.n_points
        report = {"checkpoint": args.checkpoint, "pairs_per_setting": args.pairs}
        if not args.verdict_only:
            batches = training.validation_batches(
                args.data_dir, SETTINGS, count=args.pairs, n_points=n_points, unseen=args.unseen
            )
            config = registrar.config
            grid = {k: (getattr(config, k),) for k in GRID} if args.keep_gmcce else dict(GRID)
            if args.iters:
                grid["n_iters"] = tuple(args.iters)
            report |= choose_inference(registrar, batches, grid)
            registrar = registrar.replace(**report["chosen"])
        batches = training.validation_batches(
            args.data_dir, args.verdict_settings, count=args.pairs, n_points=n_points, unseen=args.unseen
        )
        report |= choose_from_evidence(
            gather_agreement(registrar, batches), _pooled(args.verdict_settings, args.verdict_pool)
        )
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2)
    if args.record:
        record(args.checkpoint, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
