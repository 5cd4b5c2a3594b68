"""The baselines' refinement against DIT's, after the same global estimates, on validation pairs.

``fpfh_ransac_icp`` and ``fgr_icp`` refine their global estimate with the single ICP schedule tuned for them
per setting (``python tools/tune_baselines.py``); DIT + ICP uses :func:`dit_jax.geometry.icp_refine.refine`, the best fit among
several ICP runs. This asks whether the baselines would be stronger with DIT's refinement: each global
estimate (tuned options per setting) is refined both ways and scored as the tuning scores (success,
share within 5 degrees and 0.05, median rotation error). Validation pairs of training shapes only.

    python tools/compare_baseline_refinement.py --data-dir /data/modelnet40_ply_hdf5_1024 --unseen

Prints a markdown table. ``--write`` also makes it the last tuning stage: per setting, each of
``fpfh_ransac_icp`` and ``fgr_icp`` keeps whichever refinement scores better there (ties keep the single
ICP, the cheaper), and ``any`` the one better summed over the settings; the choice goes into
``dit_jax/evaluators/baselines_tuned.json`` (as ``icp_method: "refine"``, with the single ICP's method kept beside it so
the comparison can be run again) and the table into ``docs/baselines_refinement.md``.
"""

import argparse
import datetime
import json
import pathlib

import numpy as np
from tune_baselines import score  # the tuning's own score, so the two tables compare

from dit_jax import training
from dit_jax.data.pairs import SETTINGS
from dit_jax.evaluators import baselines
from dit_jax.geometry import icp_refine

ROOT = pathlib.Path(__file__).resolve().parents[1]
TUNED_PATH = ROOT / "dit_jax" / "evaluators" / baselines.TUNED_FILE


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None, help="ModelNet40 in the h5 layout (default: embedded set)")
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=16, help="validation pairs per setting")
    parser.add_argument("--points", type=int, default=1000, help="points per cloud of the validation pairs")
    parser.add_argument(
        "--write",
        action="store_true",
        help="write the per-setting choice into dit_jax/evaluators/baselines_tuned.json and the table into "
        "docs/baselines_refinement.md",
    )
    args = parser.parse_args(argv)
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # its warnings go to stdout, into the table
    batches = training.validation_batches(
        args.data_dir, list(SETTINGS), count=args.pairs, n_points=args.points, unseen=args.unseen
    )
    tuned_json = json.loads(TUNED_PATH.read_text())
    # The single ICP each method was tuned with (kept here once --write has switched a setting to "refine").
    single = tuned_json.get("refinement", {}).get("single_icp_method", {})
    command = (
        "python tools/compare_baseline_refinement.py "
        + (f"--data-dir {args.data_dir} " if args.data_dir else "")
        + ("--unseen " if args.unseen else "")
        + f"--pairs {args.pairs}"
        + (" --write" if args.write else "")
    )
    lines = [
        f"{datetime.date.today().isoformat()}: `{command}` (validation pairs of training shapes)",
        "",
        "success % / within 5 deg, 0.05 % / median deg; the better score (success + within 5) in bold",
        "",
        "| method | setting | its tuned single ICP | DIT's refinement |",
        "|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    wins = {"tuned": 0, "refine": 0, "tie": 0}
    scores = {}
    for method in ("fpfh_ransac", "fgr"):
        name = method + "_icp"
        for setting, batch in batches.items():
            options = baselines.tuned_options(name, setting)
            if options.icp_method == baselines.REFINE:
                options = options.replace(icp_method=single[name][setting])
            tuned, multi = [], []
            for i in range(len(batch["src"])):
                src, tgt = batch["src"][i].astype(np.float64), batch["tgt"][i].astype(np.float64)
                rotation, translation = baselines.get(method, setting, options)(src, tgt)
                tuned.append(baselines.refine(src, tgt, rotation, translation, options))
                refined = icp_refine.refine(src, tgt, rotation, translation)
                multi.append((refined.rotation, refined.translation))
            a, b = score(tuned, batch), score(multi, batch)
            scores.setdefault(name, {})[setting] = (a["score"], b["score"])
            cell = lambda s, bold: ("**{}**" if bold else "{}").format(
                f"{100 * s['success']:.0f} / {100 * s['within_5']:.0f} / {s['median']:.2f}"
            )
            better = "tie" if np.isclose(a["score"], b["score"]) else ("tuned" if a["score"] > b["score"] else "refine")
            wins[better] += 1
            lines.append(f"| {name} | {setting} | {cell(a, better == 'tuned')} | {cell(b, better == 'refine')} |")
            print(lines[-1], flush=True)
    lines += [
        "",
        f"The tuned single ICP scores better on {wins['tuned']} of these, DIT's refinement on "
        f"{wins['refine']}, ties {wins['tie']}.",
    ]
    print(lines[-1])
    if args.write:
        choice = tuned_json["choice"]
        # No date in the package's file: the tuning's report in docs/ carries it.
        record = {"command": command, "pairs": args.pairs, "single_icp_method": {}, "scores": scores}
        chosen = []
        for name, per_setting in scores.items():
            record["single_icp_method"][name] = {}
            for target in list(per_setting) + ["any"]:
                options = choice[name][target]
                if options["icp_method"] == baselines.REFINE:
                    options["icp_method"] = single[name][target]
                record["single_icp_method"][name][target] = options["icp_method"]
                if target == "any":
                    tuned_sum, refine_sum = (sum(v[k] for v in per_setting.values()) for k in (0, 1))
                else:
                    tuned_sum, refine_sum = per_setting[target]
                if refine_sum > tuned_sum and not np.isclose(refine_sum, tuned_sum):
                    options["icp_method"] = baselines.REFINE
                    chosen.append(f"{name} {target}")
        tuned_json["refinement"] = record
        TUNED_PATH.write_text(json.dumps(tuned_json, indent=1) + "\n")
        lines += [
            "",
            "Written to `dit_jax/evaluators/baselines_tuned.json`: DIT's refinement (`icp_method: refine`) for "
            + (", ".join(chosen) or "none")
            + "; the tuned single ICP elsewhere ('any': summed over "
            "the settings, the global estimate of each setting's own choice).",
        ]
        (ROOT / "docs" / "baselines_refinement.md").write_text(
            "# The baselines' ICP refinement: their tuned single ICP or DIT's refinement\n\n" + "\n".join(lines) + "\n"
        )


if __name__ == "__main__":
    main()
