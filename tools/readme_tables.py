"""Prints the README's summary tables of an evaluate.py output directory, from its results.json.

    python tools/readme_tables.py docs/eval_modelnet40_unseen [--before OLD/results.json]
    python tools/readme_tables.py --verdict docs/eval_stanford_dragon docs/eval_modelnet40_unseen

Two tables per directory: which method is best per setting and the runner-up (ranked by success, then the
share within 5 degrees and 0.05, then the lower mean isotropic rotation error), with DIT's and DIT+ICP's
figures beside them; and DIT against DIT+ICP and the strongest baseline, every setting. ``--before`` (an
earlier results.json of the same pairs, say from ``git show``) adds a line per setting with DIT's and
DIT+ICP's success and share within 5 degrees then and now, which is what a re-measurement after new weights
has to report. ``--verdict`` prints instead one table over every directory given (ModelNet40 settings or
scan pair sets): how many of DIT's and DIT+ICP's failures (more than 5 degrees off) the agreement verdict
flags, and how many of the results it trusts are within 5 degrees. Nothing is registered; the figures are
those evaluate.py wrote.
"""

import argparse
import json
import os

from dit_jax.evaluators import common as evaluation

#: evaluate.py's names of the network's own rows; every other method is a baseline.
NETWORK = evaluation.PIPELINE_METHODS


def rank_key(stats: dict) -> tuple:
    return (-stats["success"], -evaluation.success_share(stats), stats["rot_iso"])


def percent(x: float) -> str:
    return f"{100 * x:.0f} %"


def best_table(settings: dict) -> list[str]:
    lines = [
        "| setting | best (success, then within 5 deg, then iso R) | runner-up | " + " | ".join(NETWORK) + " |",
        "|---|---|---|" + "---|" * len(NETWORK),
    ]
    for name, methods in settings.items():
        ranked = sorted(methods, key=lambda m: rank_key(methods[m]))

        def cell(m):
            s = methods[m]
            within = percent(evaluation.success_share(s))
            return f"{m}: {percent(s['success'])} success, {within} within 5 deg, iso R {s['rot_iso']:.3g}"

        def short(m):
            return f"{percent(methods[m]['success'])} / iso {methods[m]['rot_iso']:.3g}" if m in methods else "-"

        lines.append(f"| {name} | {cell(ranked[0])} | {cell(ranked[1])} | {' | '.join(map(short, NETWORK))} |")
    return lines


def versus_table(settings: dict) -> list[str]:
    lines = [
        "| setting | method | MAE(R) deg | iso R deg | success | within 5 deg, 0.05 | s / pair |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, methods in settings.items():
        baselines = [m for m in methods if m not in NETWORK]
        shown = [m for m in NETWORK if m in methods]
        if baselines:
            shown.append(min(baselines, key=lambda m: rank_key(methods[m])))
        for m in shown:
            s = methods[m]
            lines.append(
                f"| {name} | {m} | {s['rot_mae']:.4g} | {s['rot_iso']:.4g} | {percent(s['success'])} | "
                f"{percent(evaluation.success_share(s))} | {s['seconds_per_pair']:.3f} |"
            )
    return lines


def changes(settings: dict, before: dict) -> list[str]:
    lines = []
    for name, methods in settings.items():
        parts = []
        for m in NETWORK:
            if m in methods and m in before.get(name, {}):
                old, new = before[name][m], methods[m]
                parts.append(
                    f"{m} success {percent(old['success'])} -> {percent(new['success'])}, within 5 "
                    f"{percent(evaluation.success_share(old))} -> {percent(evaluation.success_share(new))}, iso R "
                    f"{old['rot_iso']:.3g} -> {new['rot_iso']:.3g}"
                )
        if parts:
            lines.append(f"- {name}: " + "; ".join(parts))
    return lines


def _count(summary: dict | None, what: str) -> str:
    """``failures flagged`` or ``trusted right`` of an evaluation.verdict_summary as "k of n" ("-" for none)."""
    if not summary:
        return "-"
    n = summary["failures"] if what == "flagged" else summary["passed"]
    share = summary["failures_caught"] if what == "flagged" else summary["passed_right"]
    return f"{round(n * share)} of {n}" if n else "-"


def verdict_table(directories: list[str]) -> list[str]:
    lines = [
        "| data | "
        + " | ".join(f"{m}: failures (> 5 deg) flagged | {m}: trusted within 5 deg" for m in NETWORK)
        + " |",
        "|---|" + "---|---|" * len(NETWORK),
    ]
    for directory in directories:
        results = json.load(open(os.path.join(directory, "results.json")))
        if "pair_sets" in results:  # evaluate.py --scans
            groups = {
                f"{os.path.basename(results['scans'].rstrip('/'))} {name}": {
                    m: v["summary"] for m, v in methods.items()
                }
                for name, methods in results["pair_sets"].items()
            }
        else:
            groups = {
                f"{os.path.basename(directory.rstrip('/'))} {name}": methods
                for name, methods in results["settings"].items()
            }
        for name, methods in groups.items():
            pairs = methods[NETWORK[0]]["pairs"]
            verdicts = [(methods.get(m) or {}).get("verdict") for m in NETWORK]
            lines.append(
                f"| {name} ({pairs} pairs) | "
                + " | ".join(f"{_count(v, 'flagged')} | {_count(v, 'trusted')}" for v in verdicts)
                + " |"
            )
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "directory",
        nargs="+",
        help="evaluate.py --out directories (holding results.json); one, but with --verdict any number",
    )
    parser.add_argument("--before", default=None, help="an earlier results.json of the same pairs")
    parser.add_argument("--verdict", action="store_true", help="the agreement verdict's table instead")
    args = parser.parse_args(argv)
    if args.verdict:
        print("\n".join(verdict_table(args.directory)))
        return
    if len(args.directory) > 1:
        parser.error("give one directory (or --verdict)")
    results = json.load(open(os.path.join(args.directory[0], "results.json")))
    settings = results["settings"]
    print("\n".join(best_table(settings)), end="\n\n")
    print("\n".join(versus_table(settings)))
    if args.before:
        print()
        print("\n".join(changes(settings, json.load(open(args.before))["settings"])))


if __name__ == "__main__":
    main()
