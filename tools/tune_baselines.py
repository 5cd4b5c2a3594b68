"""Tunes the classical baselines (and DIT's ICP refinement) on validation pairs of training shapes, never on
test pairs, and writes the choice that evaluate.py and the API use by default.

    python tools/tune_baselines.py --data-dir /data/modelnet40_ply_hdf5_1024 --unseen

Validation pairs: the training split's held-out shapes (categories 0-19 with ``--unseen``), ``--pairs`` per
setting, every setting of :data:`dit_jax.data.pairs.SETTINGS`. Each configuration is scored per setting by
success ratio (the paper's criterion) plus the share within 5 degrees and 0.05 (a criterion that
independently sampled clouds can meet); ties go to the lower median rotation error. Per setting the best
configuration wins; ``any`` is the one with the best mean score over all settings (used where the setting is
unknown: real scans, users' clouds). The search, in stages:

1. features x distance: voxel, normal radius and FPFH radius (:data:`FEATURE_GRID`) with each distance of
   :data:`DISTANCES`, for RANSAC (100,000 iterations) and FGR (with each tuple scale);
2. RANSAC's stopping rule (:data:`RANSAC_RULES`) on each winner of stage 1;
3. the ICP refinement (:data:`SCHEDULES` x :data:`ICP_METHODS`) after each chosen global estimate, and after
   DIT's own (the model as it ships, ``--checkpoint``), and the plain ICP's distance (:data:`ICP_DISTANCES`).

Writes ``dit_jax/evaluators/baselines_tuned.json`` (the choice, read by :func:`dit_jax.evaluators.baselines.tuned`) and
``docs/baselines_tuning.md`` / ``.json`` (grid, every score, the choice). Then run
``python tools/compare_baseline_refinement.py --write``, the last stage: it lets each ``*_icp`` baseline take DIT's
own refinement (:func:`dit_jax.geometry.icp_refine.refine`) where that scores better on 48 validation pairs per setting.
"""

import argparse
import datetime
import itertools
import json
import os
import sys
import time

import jax.numpy as jnp
import numpy as np

from dit_jax import training
from dit_jax.data.pairs import SETTINGS
from dit_jax.evaluators import baselines, common, metrics
from dit_jax.geometry import icp as icp_lib
from dit_jax.pipeline import registration
from dit_jax.pipeline import settings as settings_lib

FEATURE_GRID = {"voxel": (None, 0.03), "normal_radius": (0.1, 0.2), "feature_radius": (0.15, 0.25, 0.4)}
DISTANCES = (0.025, 0.05, 0.1)
TUPLE_SCALES = (0.95, 0.9)
RANSAC_RULES = ((100_000, 0.999), (1_000_000, 0.9999))
ICP_DISTANCES = (0.05, 0.1, 0.2, 0.5)
SCHEDULES = ((0.05,), (0.1, 0.05), (0.2, 0.1, 0.05), (0.1, 0.05, 0.025))
ICP_METHODS = ("point_to_point", "point_to_plane")


def score(estimates: list, batch: dict) -> dict:
    """Success, within 5 deg / 0.05, median rotation error of estimates [(R, t)] against a batch's truth."""
    rotation = np.stack([r for r, _ in estimates])
    translation = np.stack([t for _, t in estimates])
    s = metrics.summarise(rotation, translation, batch["R"], batch["t"])
    errors = np.asarray(metrics.rotation_error_deg(jnp.asarray(rotation, jnp.float32), jnp.asarray(batch["R"])))
    within = common.success_share(s)
    return {
        "success": s["success"],
        "within_5": within,
        "median": float(np.median(errors)),
        "score": s["success"] + within,
    }


def rounded(value):
    """``value`` with every float rounded to 4 decimals (the report stays small)."""
    if isinstance(value, float):
        return round(value, 4)
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(v) for v in value]
    return value


def rank_key(row: dict):
    return (round(row["score"], 9), -row["median"])


def choose(rows: list[dict]) -> dict:
    """Per setting the best row's options, and ``any``: the best mean over settings.
    Rows: {"options": dict, "settings": {setting: score dict}}."""
    chosen = {}
    settings = rows[0]["settings"].keys()
    for setting in settings:
        best = max(rows, key=lambda r: rank_key(r["settings"][setting]))
        chosen[setting] = best
    mean = lambda r: {
        "score": np.mean([v["score"] for v in r["settings"].values()]),
        "median": np.mean([v["median"] for v in r["settings"].values()]),
    }
    chosen["any"] = max(rows, key=lambda r: rank_key(mean(r)))
    return chosen


def _pair(batch: dict, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair ``i`` of a validation batch as float64 (src (N, 3), tgt (N, 3))."""
    return batch["src"][i].astype(np.float64), batch["tgt"][i].astype(np.float64)


def _feature_grid(batches: dict, log) -> tuple[dict, dict]:
    """Stage 1: every feature setting times RANSAC's distance (and FGR's tuple scale) on every pair.

    Returns ``(estimates, options)``: per method, per options key (their sorted JSON), the estimates per
    setting and the :class:`~dit_jax.evaluators.baselines.Options` themselves; later stages reuse the estimates.
    """
    estimates = {"fpfh_ransac": {}, "fgr": {}}
    options = {"fpfh_ransac": {}, "fgr": {}}

    def keep(method: str, opt: baselines.Options, setting: str, estimate) -> None:
        key = json.dumps(opt.to_dict(), sort_keys=True)
        options[method][key] = opt
        estimates[method].setdefault(key, {}).setdefault(setting, []).append(estimate)

    feature_combos = [dict(zip(FEATURE_GRID, v)) for v in itertools.product(*FEATURE_GRID.values())]
    for setting, b in batches.items():
        for i in range(len(b["src"])):
            src, tgt = _pair(b, i)
            for combo in feature_combos:
                base = baselines.Options(**combo)
                fs, ft = baselines.features(src, base), baselines.features(tgt, base)
                for distance in DISTANCES:
                    opt = base.replace(distance=distance)
                    keep("fpfh_ransac", opt, setting, baselines.ransac_on_features(fs, ft, opt))
                    for tuple_scale in TUPLE_SCALES:
                        opt_fgr = opt.replace(fgr_tuple_scale=tuple_scale)
                        keep("fgr", opt_fgr, setting, baselines.fgr_on_features(fs, ft, opt_fgr))
        log(f"stage 1: {setting} done")
    return estimates, options


def build_parser() -> argparse.ArgumentParser:
    """tune_baselines' command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=24, help="validation pairs per setting")
    settings_lib.add_flags(parser, ("points",))  # the validation pairs' clouds are the network's size
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="the DIT model whose refinement is tuned (default: the shipped weights); 'none' skips it",
    )
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS))
    parser.add_argument("--out-json", default="dit_jax/evaluators/baselines_tuned.json")
    parser.add_argument("--report", default="docs/baselines_tuning")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if args.points is None:  # the checkpoint's own, or the pipeline's default without one
        no_dit = args.checkpoint == "none"
        args.points = (
            settings_lib.InferenceSettings().n_points
            if no_dit
            else registration.load(args.checkpoint).settings.n_points
        )
    started = time.time()
    batches = training.validation_batches(
        args.data_dir, args.settings, count=args.pairs, n_points=args.points, unseen=args.unseen
    )
    log = lambda msg: print(f"[{time.time() - started:6.0f} s] {msg}", flush=True)

    est, configs = _feature_grid(batches, log)

    def key_of(options: dict) -> str:
        return json.dumps(baselines.Options.from_dict(options).to_dict(), sort_keys=True)

    def row(method, options, estimates):
        return {"options": options, "settings": {s: score(estimates[s], batches[s]) for s in batches}}

    report = {
        "date": datetime.date.today().isoformat(),
        "command": "python tools/tune_baselines.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "pairs": args.pairs,
        "n_points": args.points,
        "unseen": args.unseen,
        "data": args.data_dir or "embedded",
        "grid": {
            "features": FEATURE_GRID,
            "distances": DISTANCES,
            "tuple_scales": TUPLE_SCALES,
            "ransac_rules": RANSAC_RULES,
            "icp_distances": ICP_DISTANCES,
            "schedules": SCHEDULES,
            "icp_methods": ICP_METHODS,
        },
        "rows": {},
        "choice": {},
    }
    chosen_rows = {}
    for method in ("fpfh_ransac", "fgr"):
        report["rows"][method] = [row(method, configs[method][k].to_dict(), v) for k, v in est[method].items()]
        chosen_rows[method] = choose(report["rows"][method])

    # Stage 2: RANSAC's stopping rule on each winner (a longer search only where it scores better).
    for winner in {key_of(r["options"]): r for r in chosen_rows["fpfh_ransac"].values()}.values():
        for iterations, confidence in RANSAC_RULES[1:]:
            opt = baselines.Options.from_dict(winner["options"]).replace(
                ransac_iterations=iterations, ransac_confidence=confidence
            )
            key = key_of(opt.to_dict())
            est["fpfh_ransac"][key] = {
                s: [baselines.fpfh_ransac(*_pair(b, i), opt) for i in range(len(b["src"]))] for s, b in batches.items()
            }
            report["rows"]["fpfh_ransac"].append(row("fpfh_ransac", opt.to_dict(), est["fpfh_ransac"][key]))
    chosen_rows["fpfh_ransac"] = choose(report["rows"]["fpfh_ransac"])
    log("stage 2 done")

    # Stage 3: refinement after each chosen global estimate, after DIT's, and the plain ICP.
    if args.checkpoint != "none":
        from dit_jax.evaluators import common

        # The network's estimates through the pipeline, one direction: what the refinements start from.
        registrar = registration.load(args.checkpoint, verdict_rule="fitness", refine="none")
        dit_est = {}
        for setting, b in batches.items():
            network = common.run_dit(registrar, list(zip(b["src"], b["tgt"])))[common.METHOD_DIT]
            dit_est[setting] = list(zip(network.rotation, network.translation))
        report["rows"]["DIT"] = [row("DIT", {}, dit_est)]
    for method in ("fpfh_ransac", "fgr", "DIT"):
        if method == "DIT":
            if "DIT" not in report["rows"]:
                continue
            starts = {"": ({}, dit_est)}
        else:
            starts = {
                key_of(r["options"]): (r["options"], est[method][key_of(r["options"])])
                for r in chosen_rows[method].values()
            }
        rows_by_start = {}
        for start_key, (options, global_est) in starts.items():
            rows_by_start[start_key] = []
            for schedule, icp_method in itertools.product(SCHEDULES, ICP_METHODS):
                refined = {s: [] for s in batches}
                for setting, b in batches.items():
                    for i, (r0, t0) in enumerate(global_est[setting]):
                        result = icp_lib.icp(
                            *_pair(b, i),
                            r0,
                            t0,
                            distances=schedule,
                            method=icp_method,
                            max_iterations=baselines.Options().icp_iterations,
                        )
                        refined[setting].append((result.rotation, result.translation))
                rows_by_start[start_key].append(
                    row(method, dict(options, icp_distances=list(schedule), icp_method=icp_method), refined)
                )
        name = f"{method.lower()}_icp"
        report["rows"][name] = [r for rows in rows_by_start.values() for r in rows]
        # Each target refines the global estimate chosen for it.
        chosen_rows[name] = {}
        targets = chosen_rows[method] if method != "DIT" else {t: None for t in chosen_rows["fpfh_ransac"]}
        for target, global_row in targets.items():
            rows = rows_by_start[key_of(global_row["options"]) if global_row else ""]
            chosen_rows[name][target] = choose(rows)[target]
        log(f"stage 3: {name} done")
    report["rows"]["icp"] = [
        row(
            "icp",
            baselines.Options(icp_distances=(d,)).to_dict(),
            {
                s: [baselines.icp(*_pair(b, i), baselines.Options(icp_distances=(d,))) for i in range(len(b["src"]))]
                for s, b in batches.items()
            },
        )
        for d in ICP_DISTANCES
    ]
    chosen_rows["icp"] = choose(report["rows"]["icp"])

    # The choice: options per method and setting, with its validation scores.
    defaults = baselines.Options().to_dict()
    for method, per_target in chosen_rows.items():
        report["choice"][method] = {}
        for target, row in per_target.items():
            options = (
                dict(defaults, **row["options"])
                if method != "dit_icp"
                else {"icp_distances": row["options"]["icp_distances"], "icp_method": row["options"]["icp_method"]}
            )
            report["choice"][method][target] = {"options": options, "validation": row["settings"]}
    report["seconds"] = time.time() - started
    os.makedirs(os.path.dirname(args.report) or ".", exist_ok=True)
    with open(args.report + ".json", "w") as f:
        json.dump(rounded(report), f, separators=(",", ":"))
    # No date in the package's file: the report in docs/ carries it.
    shipped = {
        "command": report["command"],
        "report": args.report + ".md",
        "choice": {m: {t: c["options"] for t, c in per.items()} for m, per in report["choice"].items()},
    }
    with open(args.out_json, "w") as f:
        json.dump(shipped, f, indent=1)
    with open(args.report + ".md", "w") as f:
        f.write(markdown(report))
    log(f"wrote {args.out_json}, {args.report}.md and .json")


def markdown(report: dict) -> str:
    grid = report["grid"]
    lines = [
        f"# Baselines tuned on validation pairs ({report['date']})",
        "",
        f"Command: `{report['command']}` ({report['seconds'] / 60:.0f} min on this machine's 2 CPU cores).",
        "",
        f"Validation pairs: {report['pairs']} per setting, {report['n_points']} points, from the held-out "
        f"shapes of the training split of {report['data']}"
        + (" (categories 0-19)" if report["unseen"] else "")
        + "; never a test pair. Score per setting: success ratio (paper) + share within 5 deg and 0.05; "
        "ties: lower median rotation error. `any` is the best mean over settings (real scans, users' clouds).",
        "",
        "Grid:",
        "",
        f"- features: voxel {grid['features']['voxel']}, normal radius {grid['features']['normal_radius']}, "
        f"FPFH radius {grid['features']['feature_radius']} (30 / 100 neighbours at most)",
        f"- RANSAC / FGR distance {list(grid['distances'])}; FGR tuple scale {list(grid['tuple_scales'])}; "
        f"RANSAC (iterations, confidence) {[list(r) for r in grid['ransac_rules']]} (the second on stage-1 winners)",
        f"- refinement after each chosen global estimate and after DIT's: pairing distances "
        f"{[list(s) for s in grid['schedules']]} x {list(grid['icp_methods'])}",
        f"- plain ICP from the identity: distance {list(grid['icp_distances'])}",
        "",
        "## Choice and its validation scores (success / within 5 deg / median deg)",
        "",
    ]
    settings = list(next(iter(report["choice"]["fpfh_ransac"].values()))["validation"])
    lines += [
        "| method | chosen for | options | " + " | ".join(settings) + " |",
        "|---|---|---|" + "---|" * len(settings),
    ]
    features = ("voxel", "normal_radius", "feature_radius", "distance")
    shown = {
        "fpfh_ransac": features + ("ransac_iterations",),
        "fgr": features + ("fgr_tuple_scale",),
        "icp": ("icp_distances",),
        "dit_icp": ("icp_distances", "icp_method"),
    }
    shown["fpfh_ransac_icp"] = shown["fpfh_ransac"] + shown["dit_icp"]
    shown["fgr_icp"] = shown["fgr"] + shown["dit_icp"]
    for method, per_target in report["choice"].items():
        for target, c in per_target.items():
            opts = ", ".join(f"{k}={c['options'][k]}" for k in shown[method])
            cells = " | ".join(
                f"{100 * v['success']:.0f} / {100 * v['within_5']:.0f} / {v['median']:.2f}"
                for v in c["validation"].values()
            )
            lines.append(f"| {method} | {target} | {opts} | {cells} |")
    if "DIT" in report["rows"]:
        cells = " | ".join(
            f"{100 * v['success']:.0f} / {100 * v['within_5']:.0f} / {v['median']:.2f}"
            for v in report["rows"]["DIT"][0]["settings"].values()
        )
        lines.append(f"| DIT alone (shipped) | - | - | {cells} |")
    lines += ["", "Every row of the grid, with its scores, is in baselines_tuning.json.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
