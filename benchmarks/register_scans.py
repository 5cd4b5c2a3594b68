"""The default pipeline beside FPFH + RANSAC + ICP on real scans: pairs registered and seconds per pair.

    python benchmarks/register_scans.py ../shared/data/3dmatch_redkitchen ../shared/data/lidar_pair \\
        ../shared/data/stanford_dragon_stand
    python benchmarks/register_scans.py ../shared/data/3dmatch --max-pairs 40 --baseline open3d_room_5cm

For each folder of scans with known poses (any layout of :mod:`dit_jax.data.scans`) and each of its pair sets:
the shipped weights through `Registrar.register` with their own settings (sampling, network both ways,
refinement, verdict and, where the result is not trusted, the second candidate), timed whole per pair after
one untimed call that compiles; and a baseline as evaluate.py runs it (through Open3D): by default
Open3D's FPFH + RANSAC + ICP at its tuned options, ``--baseline open3d_room_5cm`` Open3D's room recipe.
``--max-pairs``: a seeded sample of a benchmark's list (the first pairs of a series), as evaluate.py takes.
A pair is registered by its benchmark's criterion (dit_jax.data.scans.CRITERIA), else within 5 degrees. Prints
one JSON record per pair set (``confirmed_max_s``: the slowest pair whose result was trusted, the figure
the 1.5 s target is about), then a Markdown table.

``--pairs-out FILE`` also writes one JSON line per pair (both methods' errors, the benchmark's RMSE where the
data define one, seconds, the pipeline's level, candidate, the evidence its verdict read and its motion as a 3 x 4 ``[R | t]``) and resumes from the pairs FILE holds, so a run
over whole benchmark lists survives an interruption; each set's record then adds the benchmark's figures
(``figures``: dit_jax.evaluators.scans.benchmark_summary of each method) and the verdict's (``exit_0``: the
results trusted or unconfirmed and how many were right; ``flagged``: the wrong results and how many were
"probably wrong"), by the set's criterion and by the benchmark's RMSE.

    python benchmarks/register_scans.py ../shared/data/3dmatch --baseline open3d_room_5cm \\
        --pairs-out runs/rooms_pairs.jsonl --record docs/rooms_full_lists.jsonl

``--descriptor runs/features-{scene}/descriptor`` registers each pair with the learned descriptor trained with
its scene left out (benchmarks/descriptor_folds.py).

``--record`` writes the per-set records to a file: docs/rooms_full_lists.jsonl is the one the rooms' full-list
table of docs/results.md and the README is generated from (python tools/results_page.py).
"""

import argparse
import datetime
import json
import os
import time

import numpy as np


def registered(row: dict, criterion) -> bool:
    """Whether a :func:`pair_row` is within the data's criterion (degrees, distance), else within 5 degrees."""
    degrees, distance = criterion or (5.0, np.inf)
    return bool(row["rot_err"] <= degrees and row["trans_err"] <= distance)


def _finite(value: float) -> float | None:
    """A float for JSON: None for NaN or inf."""
    return float(value) if np.isfinite(value) else None


def pair_row(pair, rotation, translation, seconds: float) -> dict:
    """One method's row for a pair, in the form dit_jax.evaluators.scans.benchmark_summary reads."""
    from dit_jax.data import scans as scans_lib
    from dit_jax.geometry import rigid

    rmse = scans_lib.benchmark_rmse(rotation, translation, pair)
    return {
        "rot_err": float(rigid.rotation_angle_deg(np.asarray(rotation).T @ pair.rotation)),
        "trans_err": float(np.linalg.norm(np.asarray(translation) - pair.translation)),
        "rmse": None if np.isnan(rmse) else float(rmse),
        "seconds": float(seconds),
        "scene": pair.scene,
        "consecutive": bool(pair.consecutive),
    }


def verdict_figures(lines: list[dict], right) -> dict:
    """``exit_0``: [results trusted or unconfirmed, of them right]; ``flagged``: [wrong results, of them
    "probably wrong"], where ``right(line)`` says whether the pipeline's result was right."""
    exit_0 = [line for line in lines if line["level"] != "probably wrong"]
    wrong = [line for line in lines if not right(line)]
    return {
        "exit_0": [len(exit_0), sum(map(right, exit_0))],
        "flagged": [len(wrong), sum(line["level"] == "probably wrong" for line in wrong)],
    }


def set_figures(lines: list[dict], baseline: str, criterion) -> dict:
    """The benchmark's and the verdict's figures of one pair set's per-pair lines (``--pairs-out``)."""
    from dit_jax.data.scans import BENCHMARK_RMSE
    from dit_jax.evaluators.scans import benchmark_summary

    criterion = criterion or (5.0, np.inf)

    def within(row) -> bool:
        return row["rot_err"] <= criterion[0] and row["trans_err"] <= criterion[1]

    out = {"verdict": {"criterion": verdict_figures(lines, lambda line: within(line["pipeline"]))}}
    if any(line["pipeline"]["rmse"] is not None for line in lines):
        # Benchmark lists: a pair without an information matrix counts as not registered, as the benchmark does.
        def rmse_right(row) -> bool:
            return row["rmse"] is not None and row["rmse"] <= BENCHMARK_RMSE

        out["verdict"]["rmse"] = verdict_figures(lines, lambda line: rmse_right(line["pipeline"]))
        methods = ["pipeline"] + ([baseline] if all(baseline in line for line in lines) else [])
        rows = {m: [line[m] | {"rmse": line[m]["rmse"] or np.inf} for line in lines] for m in methods}
        out["figures"] = {m: benchmark_summary(rows[m], criterion) for m in methods}
        if len(methods) == 2:
            ok = {m: [rmse_right(line[m]) for line in lines] for m in methods}
            out["only"] = {
                m: [line["pair"] for line, a, b in zip(lines, ok[m], ok[methods[1 - k]]) if a and not b]
                for k, m in enumerate(methods)
            }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument("--no-baseline", action="store_true", help="time the pipeline alone")
    parser.add_argument(
        "--baseline", default="fpfh_ransac_icp", help="a name of dit_jax.evaluators.baselines.SCAN_BASELINES"
    )
    parser.add_argument("--max-pairs", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0, help="the sample's seed")
    parser.add_argument("--pairs-out", default=None, help="write (and resume from) one JSON line per pair")
    parser.add_argument("--record", default=None, help="also write the per-set records to this file (JSON lines)")
    parser.add_argument("--viewpoint", choices=("origin", "none"), default=None, help="the pipeline's viewpoint")
    parser.add_argument(
        "--descriptor",
        default=None,
        help="the pipeline's descriptor: fpfh, histograms, learned or a weights directory ({scene}: each pair's scene)",
    )
    args = parser.parse_args()
    baseline = args.baseline

    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import register_baseline, sample_pairs
    from dit_jax.pipeline import registration

    changes = {name: getattr(args, name) for name in ("viewpoint", "descriptor") if getattr(args, name)}
    models = {}

    def model_of(scene: str):
        """The pipeline for a pair of ``scene``: a ``--descriptor`` naming ``{scene}`` takes that scene's
        weights (a learned descriptor trained with the scene left out)."""
        scene_changes = changes | ({"descriptor": args.descriptor.format(scene=scene)} if args.descriptor else {})
        key = scene_changes.get("descriptor")
        if key not in models:
            models[key] = registration.load(**scene_changes)
        return models[key]

    warmed = set()

    done = {}
    if args.pairs_out and os.path.exists(args.pairs_out):
        with open(args.pairs_out) as f:
            done = {(line["data"], line["set"], line["pair"]): line for line in map(json.loads, f)}
    pairs_file = open(args.pairs_out, "a") if args.pairs_out else None
    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            data = os.path.basename(os.path.normpath(folder))
            pairs = sample_pairs(found, args.max_pairs, args.seed)
            pipeline_s, pipeline_ok, confirmed_s, trusted, trusted_right = [], 0, [], 0, 0
            baseline_s, baseline_ok = [], 0
            lines = []
            for pair in pairs:
                line = done.get((data, set_name, pair.name))
                if line is None:
                    model = model_of(pair.scene)
                    if (id(model), folder, set_name) not in warmed:  # compiles (or warms) once per folder's sizes
                        model.register(pair.source, pair.target)
                        warmed.add((id(model), folder, set_name))
                    started = time.perf_counter()
                    result = model.register(pair.source, pair.target)
                    seconds = time.perf_counter() - started
                    line = {"data": data, "set": set_name, "pair": pair.name, "level": result.level}
                    line |= {"candidate": result.candidate, "confirmed": bool(result.verdict)}
                    line |= {"rival": _finite(result.rival), "twin": _finite(result.twin)}
                    line |= {"agreement": _finite(result.agreement), "offset": _finite(result.offset)}
                    line |= {"fitness": _finite(result.fitness), "inlier_ratio": _finite(result.inlier_ratio)}
                    line["pipeline"] = pair_row(pair, result.rotation, result.translation, seconds)
                    line["motion"] = np.c_[result.rotation, result.translation].round(7).tolist()
                    if not args.no_baseline:
                        line[baseline] = pair_row(pair, *register_baseline(baseline, pair.source, pair.target))
                    if pairs_file:
                        pairs_file.write(json.dumps(line) + "\n")
                        pairs_file.flush()
                lines.append(line)
                pipeline_s.append(line["pipeline"]["seconds"])
                ok = registered(line["pipeline"], found.criterion)
                pipeline_ok += ok
                trusted += line["level"] == "trusted"
                trusted_right += line["level"] == "trusted" and ok
                if line["confirmed"]:
                    confirmed_s.append(pipeline_s[-1])
                if baseline in line:
                    baseline_s.append(line[baseline]["seconds"])
                    baseline_ok += registered(line[baseline], found.criterion)
            record = {
                "benchmark": "register_scans",
                "date": datetime.date.today().isoformat(),
                "cpus": os.cpu_count(),
                "data": data,
                "set": set_name,
                "pairs": len(pairs),
                "points": [
                    min(min(len(p.source), len(p.target)) for p in pairs),
                    max(max(len(p.source), len(p.target)) for p in pairs),
                ],
                "criterion": found.criterion,
                "pipeline": {
                    "registered": int(pipeline_ok),
                    "trusted": int(trusted),
                    "trusted_right": int(trusted_right),
                    "median_s": float(np.median(pipeline_s)),
                    "max_s": float(np.max(pipeline_s)),
                    "confirmed_pairs": len(confirmed_s),
                    "confirmed_max_s": float(np.max(confirmed_s)) if confirmed_s else None,
                },
            }
            if args.pairs_out:
                record |= set_figures(lines, baseline, found.criterion)
            if baseline_s:
                record[baseline] = {
                    "registered": int(baseline_ok),
                    "median_s": float(np.median(baseline_s)),
                    "max_s": float(np.max(baseline_s)),
                }
            print(json.dumps(record), flush=True)
            records.append(record)
    if args.record:
        with open(args.record, "w") as f:
            f.writelines(json.dumps(record) + "\n" for record in records)
    print(f"\n{datetime.date.today().isoformat()}, {os.cpu_count()} CPUs, shipped weights with their settings\n")
    print(
        f"| data | pairs | points a cloud | pipeline: registered, trusted (right) | pipeline s / pair: median, "
        f"max, max where trusted | {baseline}: registered | {baseline} s / pair: "
        "median, max |\n|---|---|---|---|---|---|---|"
    )
    for r in records:
        p, b = r["pipeline"], r.get(baseline)
        confirmed = "-" if p["confirmed_max_s"] is None else f"{p['confirmed_max_s']:.2f}"
        print(
            f"| {r['data']} {r['set']} | {r['pairs']} | {r['points'][0]:,}-{r['points'][1]:,} | "
            f"{p['registered']}, {p['trusted']} ({p['trusted_right']}) | {p['median_s']:.2f}, {p['max_s']:.2f}, "
            f"{confirmed} | " + (f"{b['registered']} | {b['median_s']:.2f}, {b['max_s']:.2f} |" if b else "- | - |")
        )


if __name__ == "__main__":
    main()
