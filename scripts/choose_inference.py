"""Chooses a model's inference settings and its verdict threshold on validation pairs, never on test pairs.

    python scripts/choose_inference.py runs/mix/model --data-dir ../shared/data/modelnet40_ply_hdf5_1024 \
        --out runs/mix/inference_choice.json

Validation pairs are made from the training split's held-out shapes (the same ones training validates on,
categories 0-19 with ``--unseen``), for the authors' settings and those whose clouds share no point. Every
combination of GMCCE threshold, ``gmcce_min_keep`` and ``guard_iterations`` in the grid registers them; the
one with the most pairs within 5 degrees, averaged over the settings (ties: the lower mean log error), wins:
one setting for every input. The fitness verdict's threshold is then the lowest fitness at which at least 95 %
of the results it trusts are within 5 degrees, over all settings' pairs pooled.

The agreement verdict (the default of ``register``) is chosen the same way, on every setting (``--verdict-settings``):
each pair is also registered target onto source, alone and refined by ICP as ``register`` does, and each
threshold (``verdict_max_disagreement``, per refinement) is the largest of :data:`AGREEMENT_GRID` at which at
least 95 % of the results it trusts are within 5 degrees, pooled over the settings whose clouds share no point
(``--verdict-pool independent``, the default since 2026-11-28: users' data never shares points, and the
authors' settings, nearly all right and agreeing, would loosen the threshold for everyone; ``all`` pools
every setting, as before). The figures on every setting are reported beside it. DIT+ICP's errors are those
of the motion ``register`` returns: with ``best_direction`` (the default) the better fitting of the two refined
directions.

    python scripts/choose_inference.py dit_jax/weights/dit-cpu-modelnet40 --verdict-only --record \
        --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --pairs 64 --out runs/verdict_choice.json

``--verdict-only`` keeps the checkpoint's inference settings and chooses the agreement thresholds alone;
``--record`` writes them into the checkpoint's record (the weights themselves are not touched). Give the
verdict as many pairs as time allows: precision sits near 95 % over a band of thresholds, so the sample moves
the pick (the sixth stage's weights: 0.25 degrees on 32 pairs per setting, 3 on 48, 1.5 on 64, 0.5 on 128;
docs/BENCHMARKS.md). The output keeps every pair's error and agreement and the precision curve.

Where no threshold reaches 95 % on the pool (the network alone on the sixth stage's weights, 128 pairs), the
smallest of the grid is taken and named in the record (``verdict_fallback``). ``--rechoose OUT.json`` makes
the choice again from the per-pair evidence an earlier ``--out`` kept, registering nothing:

    python scripts/choose_inference.py dit_jax/weights/dit-cpu-modelnet40 --rechoose runs/verdict_choice.json \
        --record --out runs/verdict_rechoice.json

``--n-iters 3 5 8`` adds the number of registration iterations to the grid; with ``--keep-gmcce`` it is the
only thing searched (the checkpoint's GMCCE options and guard stay). With ``--record`` the chosen settings go
into the checkpoint's config (:func:`dit_jax.checkpoint.update_config`) and both verdicts' thresholds into its
record:

    python scripts/choose_inference.py dit_jax/weights/dit-cpu-modelnet40 --keep-gmcce --n-iters 3 5 8 \
        --record --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --pairs 32 --out runs/iters.json
"""

import argparse
import datetime
import itertools
import json
import os

import jax.numpy as jnp
import numpy as np

from dit_jax import checkpoint, evaluation, geometry, metrics, model, registration, training
from dit_jax.data import pairs as pairs_lib

SETTINGS = ("clean", "low_noise_partial", "high_noise_partial", "independent_clean", "scan_high_noise")
#: Candidate thresholds (degrees) of the agreement verdict.
AGREEMENT_GRID = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
#: A verdict threshold must leave at least this share of the results it trusts within ``RIGHT_DEG``.
PRECISION = 0.95
RIGHT_DEG = 5.0


def largest_threshold(errors: np.ndarray, agreement: np.ndarray) -> float | None:
    """The largest :data:`AGREEMENT_GRID` value at which at least :data:`PRECISION` of the results with
    ``agreement`` (P,) at or below it have ``errors`` (P,) within :data:`RIGHT_DEG`; None if none does."""
    chosen = None
    for threshold in AGREEMENT_GRID:
        trusted = agreement <= threshold
        if trusted.any() and np.mean(errors[trusted] <= RIGHT_DEG) >= PRECISION:
            chosen = threshold
    return chosen


def choose_agreement(params, config, batches: dict, pool: str = "independent",
                     best_direction: bool = registration.DEFAULT_BEST_DIRECTION) -> dict:
    """The agreement verdict's thresholds per refinement on ``batches`` ({setting: validation batch}), chosen
    on the pairs of ``pool``'s settings ("independent": those whose clouds share no point, where there are
    any; "all"), with what they do on those pairs, per setting, over the pool and over all.
    ``best_direction``: DIT+ICP's errors are those of the better fitting refined direction, as ``register``
    returns it (else the forward one's)."""
    found = {"none": ([], [], []), "icp": ([], [], [])}
    for setting, b in batches.items():
        pairs = pairs_lib.PairView(b)
        indices = np.arange(len(b["src"]))
        forward = evaluation.predict_dit(params, config, pairs, indices)
        refined = evaluation.refine_dit(forward, pairs, indices, truth_fit=False)
        agreement = evaluation.backward_agreement(params, config, pairs, indices, forward, refined)
        if best_direction:
            refined = evaluation.choose_direction(refined, agreement[evaluation.METHOD_DIT_ICP], pairs, indices)
        for refinement, pred, method in (("none", forward, evaluation.METHOD_DIT),
                                         ("icp", refined, evaluation.METHOD_DIT_ICP)):
            errors = np.array([geometry.rotation_angle_deg(r.T @ t) for r, t in zip(pred["R"], b["R"])])
            found[refinement][0].append(errors)
            found[refinement][1].append(agreement[method]["agreement"])
            found[refinement][2].append(np.full(len(errors), setting))
        print(f"{setting}: agreement gathered", flush=True)
    pooled = [s for s in batches if pool == "all" or pairs_lib.SETTINGS[s].independent] or list(batches)
    per_pair = {}
    for refinement, (errors, agreement, settings) in found.items():
        errors, agreement, settings = map(np.concatenate, (errors, agreement, settings))
        per_pair[refinement] = {"setting": settings.tolist(), "rot_err": np.round(errors, 5).tolist(),
                                "agreement": np.round(agreement, 5).tolist()}
    return choose_from_evidence(per_pair, pooled)


def fallback_threshold(curve: list[dict]) -> float:
    """The :data:`AGREEMENT_GRID` threshold whose trusted results are most often right on ``curve`` (one
    :func:`dit_jax.evaluation.verdict_summary` per grid value), the smaller on a tie. A threshold that trusts
    none of the results counts as always right (it trusts none wrongly); one that trusts fewer than
    :data:`dit_jax.registration.MIN_BAND_PAIRS` is not taken (too few to say how often they are right), unless
    every threshold is such, when the smallest is."""
    candidates = [(1.0 if row["passed"] == 0 else row["passed_right"], -t) for t, row in zip(AGREEMENT_GRID, curve)
                  if row["passed"] == 0 or row["passed"] >= registration.MIN_BAND_PAIRS]
    return -max(candidates)[1] if candidates else AGREEMENT_GRID[0]


def choose_from_evidence(per_pair: dict, pooled: list[str]) -> dict:
    """The agreement thresholds per refinement from evidence already gathered: ``per_pair`` {refinement:
    {"setting", "rot_err", "agreement"}, each (P,)}, as :func:`choose_agreement` keeps it (so a saved choice
    can be made again, or by another rule, without registering the pairs again); ``pooled``: the settings the
    threshold is chosen over.

    Where no threshold of the grid reaches :data:`PRECISION` on the pool, the fallback (recorded under
    ``verdict_fallback``) is the one whose trusted pool results are most often right (:func:`fallback_threshold`;
    often the smallest, which trusts none of the pool): the verdict then trusts only close agreement, as pairs
    that share their points give, and flags nearly every result on the pool, rather than trust results that are
    too often wrong. (Until 2026-12-02 it was always the smallest, which can be the less precise: the seventh
    stage's weights, 128 pairs per setting, DIT+ICP: 0.25 degrees trusted 11 pool results, 90.9 % right, 0.5
    trusted 57, 94.7 % right.)"""
    report = {"verdict_max_disagreement": {}, "verdict_pool": list(pooled), "verdict_agreement_on_validation": {},
              "verdict_curve": {}, "verdict_agreement_bands": {}, "per_pair": per_pair, "verdict_fallback": []}
    for refinement, evidence in per_pair.items():
        errors, agreement = np.asarray(evidence["rot_err"], float), np.asarray(evidence["agreement"], float)
        settings = np.asarray(evidence["setting"])
        in_pool = np.isin(settings, pooled)
        report["verdict_curve"][refinement] = curve = [
            evaluation.verdict_summary(errors[in_pool], agreement[in_pool] <= t, evaluation.agreement_rule(t),
                                       RIGHT_DEG) for t in AGREEMENT_GRID]
        print(f"refine={refinement}, over the pool: threshold / trusted / of them within {RIGHT_DEG:g} deg / "
              f"failures flagged: " + "; ".join(
                  f"{t:g} / {c['passed']} / {c['passed_right']:.3f} / {c['failures_caught']:.3f}"
                  for t, c in zip(AGREEMENT_GRID, curve)), flush=True)
        report["verdict_agreement_bands"][refinement] = evaluation.agreement_bands(
            errors[in_pool], agreement[in_pool], AGREEMENT_GRID, RIGHT_DEG)
        threshold = largest_threshold(errors[in_pool], agreement[in_pool])
        if threshold is None:
            threshold = fallback_threshold(curve)
            report["verdict_fallback"].append(refinement)
            print(f"refine={refinement}: no threshold keeps {PRECISION:.0%} of its trusted results right; "
                  f"{threshold:g} deg, the most precise (fallback_threshold), is taken", flush=True)
        report["verdict_max_disagreement"][refinement] = threshold
        rule = evaluation.agreement_rule(threshold)
        report["verdict_agreement_on_validation"][refinement] = {
            "pooled": evaluation.verdict_summary(errors, agreement <= threshold, rule, RIGHT_DEG),
            "pool": evaluation.verdict_summary(errors[in_pool], agreement[in_pool] <= threshold, rule, RIGHT_DEG),
            **{s: evaluation.verdict_summary(errors[settings == s], agreement[settings == s] <= threshold, rule,
                                             RIGHT_DEG) for s in dict.fromkeys(settings.tolist())}}
        print(f"refine={refinement}: agreement within {threshold} deg; "
              + evaluation.verdict_line("the pool", report["verdict_agreement_on_validation"][refinement]["pool"])
              + " " + evaluation.verdict_line("all", report["verdict_agreement_on_validation"][refinement]["pooled"]))
    return report


def bands_from_record(path: str) -> dict:
    """The agreement bands (:func:`dit_jax.evaluation.agreement_bands`) of a checkpoint whose thresholds were
    chosen before bands were recorded, from the precision curve its record keeps (cumulative over
    :data:`AGREEMENT_GRID`): each band's pairs and right results are the differences between neighbouring
    thresholds' trusted counts, the last band what the largest threshold left of the pool."""
    choice = checkpoint.read_extra(path)["verdict_agreement_choice"]
    pool_pairs = choice["pairs_per_setting"] * len(choice["verdict_pool"])
    bands = {}
    for refinement, curve in choice["verdict_curve"].items():
        if [row["rule"] for row in curve] != [evaluation.agreement_rule(t) for t in AGREEMENT_GRID]:
            raise ValueError(f"{path}: the recorded {refinement} curve is not over {AGREEMENT_GRID}")
        passed = [row["passed"] for row in curve]
        right = [round(row["passed"] * row["passed_right"]) if row["passed"] else 0 for row in curve]
        rows, before = [], (0, 0)
        for t, n, k in zip(AGREEMENT_GRID, passed, right):
            rows.append([t, n - before[0], k - before[1]])
            before = (n, k)
        all_right = pool_pairs - curve[-1]["failures"]
        rows.append([None, pool_pairs - before[0], all_right - before[1]])
        bands[refinement] = rows
    return bands


def record(path: str, report: dict) -> None:
    """Writes the choice into the checkpoint at ``path``, its params untouched: the agreement thresholds
    and, where inference settings were chosen too, those settings (into its config) and the fitness
    threshold, with what they did on validation (into its record). A sentence naming the new thresholds, the
    old ones and the sample is appended to the record's free-text ``note``, so the note never contradicts them."""
    before = checkpoint.read_extra(path)
    thresholds = report["verdict_max_disagreement"]
    changes = {"verdict_max_disagreement": thresholds,
               "verdict_agreement_choice": {k: report[k] for k in ("settings_verdict", "verdict_pool",
                                                                   "pairs_per_setting", "verdict_curve",
                                                                   "verdict_agreement_on_validation",
                                                                   "verdict_fallback") if k in report}}
    if "verdict_agreement_bands" in report:
        changes["verdict_agreement_bands"] = report["verdict_agreement_bands"]
    if "chosen" in report:
        config = checkpoint.update_config(path, report["chosen"])
        changes["verdict_min_fitness"] = report["verdict_min_fitness"]
        changes["inference_choice"] = {k: report[k] for k in ("chosen", "verdict_min_fitness", "settings",
                                                              "pairs_per_setting", "grid") if k in report}
        changes["inference_choice"]["verdict_on_validation"] = report.get("verdict_on_validation")
        print(f"recorded {json.dumps(report['chosen'])} in {path}'s config (n_iters {config.n_iters})")
    old = before.get("verdict_max_disagreement") or {}
    pool = ("the settings whose clouds share no point"
            if all(pairs_lib.SETTINGS[s].independent for s in report.get("verdict_pool", ())) else "every setting")
    sentence = (f"Verdict (agreement) thresholds chosen on {datetime.date.today().isoformat()} by "
                f"scripts/choose_inference.py on {report.get('pairs_per_setting', '?')} validation pairs per setting, "
                f"pooled over {pool}: {thresholds.get('none')} deg alone, {thresholds.get('icp')} with ICP"
                + (f" (were {old.get('none')} and {old.get('icp')})" if old else "")
                + (f"; no threshold kept {PRECISION:.0%} right for "
                   f"{' and '.join({'none': 'the network alone', 'icp': 'DIT+ICP'}[r] for r in report['verdict_fallback'])}, "
                   f"so the one whose trusted results were most often right was taken" if report.get("verdict_fallback") else "")
                + ".")
    changes["note"] = (before.get("note", "") + " " + sentence).strip()
    checkpoint.update_extra(path, changes)
    print(f"recorded the verdict thresholds in {path}: {sentence}")


GRID = {"gmcce_threshold": (0.9, 0.0), "gmcce_min_keep": (0.0, 0.3), "guard_iterations": (False, True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=24, help="validation pairs per setting")
    parser.add_argument("--n-points", type=int, default=1000)
    parser.add_argument("--out", required=True)
    parser.add_argument("--verdict-settings", nargs="+", default=list(pairs_lib.SETTINGS),
                        help="settings the agreement verdict is chosen on (default: all)")
    parser.add_argument("--verdict-pool", choices=("independent", "all"), default="independent",
                        help="settings the agreement thresholds are chosen over: those whose clouds share no "
                             "point (default) or all")
    parser.add_argument("--verdict-only", action="store_true",
                        help="keep the checkpoint's inference settings; choose the agreement thresholds only")
    parser.add_argument("--record", action="store_true",
                        help="write the choice into the checkpoint (settings into its config, thresholds into "
                             "its record; the params are not touched)")
    parser.add_argument("--bands-from-record", action="store_true",
                        help="record the agreement bands of a checkpoint chosen before they were kept, from the "
                             "precision curve in its record (registers nothing; --out gets them too)")
    parser.add_argument("--rechoose", default=None, metavar="JSON",
                        help="choose the agreement thresholds again from the per-pair evidence an earlier "
                             "--out of this script kept (registers nothing; the evidence must be this "
                             "checkpoint's)")
    parser.add_argument("--n-iters", type=int, nargs="+", default=None,
                        help="registration iteration counts to try as well (default: the checkpoint's only)")
    parser.add_argument("--keep-gmcce", action="store_true",
                        help="keep the checkpoint's GMCCE options and guard; search only --n-iters")
    args = parser.parse_args()

    if args.bands_from_record:
        bands = bands_from_record(args.checkpoint)
        checkpoint.update_extra(args.checkpoint, {"verdict_agreement_bands": bands})
        with open(args.out, "w") as f:
            json.dump({"checkpoint": args.checkpoint, "verdict_agreement_bands": bands}, f, indent=1)
        print(f"recorded the agreement bands in {args.checkpoint}: {json.dumps(bands)}")
        return
    if args.rechoose:
        with open(args.rechoose) as f:
            earlier = json.load(f)
        if os.path.realpath(earlier.get("checkpoint", args.checkpoint)) != os.path.realpath(args.checkpoint):
            parser.error(f"{args.rechoose} holds the evidence of {earlier['checkpoint']}, not {args.checkpoint}")
        settings = list(dict.fromkeys(earlier["per_pair"]["icp"]["setting"]))
        pooled = [s for s in settings if args.verdict_pool == "all" or pairs_lib.SETTINGS[s].independent] or settings
        report = {"checkpoint": args.checkpoint, "rechosen_from": args.rechoose,
                  **{k: earlier[k] for k in ("settings_verdict", "pairs_per_setting") if k in earlier},
                  **choose_from_evidence(earlier["per_pair"], pooled)}
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
        if args.record:
            record(args.checkpoint, report)
        return
    params, config = checkpoint.restore(args.checkpoint)
    if args.verdict_only:
        batches = training.validation_batches(args.data_dir, args.verdict_settings, count=args.pairs,
                                              n_points=args.n_points, unseen=args.unseen)
        report = {"checkpoint": args.checkpoint, "settings_verdict": args.verdict_settings,
                  "pairs_per_setting": args.pairs} | choose_agreement(params, config, batches, args.verdict_pool)
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
        if args.record:
            record(args.checkpoint, report)
        return
    batches = training.validation_batches(args.data_dir, SETTINGS, count=args.pairs, n_points=args.n_points,
                                          unseen=args.unseen)

    grid = {k: (getattr(config, k),) for k in GRID} if args.keep_gmcce else dict(GRID)
    if args.n_iters:
        grid["n_iters"] = tuple(args.n_iters)
    variants = []
    for values in itertools.product(*grid.values()):
        changes = dict(zip(grid, values))
        if changes["gmcce_threshold"] == 0.0 and changes["gmcce_min_keep"] > 0:
            continue  # a zero threshold keeps every match already
        variants.append(changes)
    report = {"checkpoint": args.checkpoint, "settings": SETTINGS, "pairs_per_setting": args.pairs,
              "grid": {k: list(v) for k, v in grid.items()}, "variants": []}
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
    verdict_batches = training.validation_batches(args.data_dir, args.verdict_settings, count=args.pairs,
                                                  n_points=args.n_points, unseen=args.unseen)
    report |= {"settings_verdict": args.verdict_settings} | choose_agreement(
        params, config.replace(**best["changes"]), verdict_batches, args.verdict_pool)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2)
    if args.record:
        record(args.checkpoint, report)


if __name__ == "__main__":
    main()
