"""Re-scores the agreement verdict in evaluation outputs at a checkpoint's current thresholds, from the
agreement every pair kept (``per_pair`` in results.json; rows of real-scan outputs): for a threshold chosen
again (``scripts/choose_inference.py --rechoose ... --record``) without registering the test pairs again.
Only the verdict lines of results.md and the verdict entries of results.json change.

    python scripts/rescore_verdict.py dit_jax/weights/dit-cpu-modelnet40 docs/eval_modelnet40_unseen \
        docs/eval_modelnet40_seen docs/eval_embedded docs/eval_modelnet40_unseen_peers docs/eval_stanford_dragon

Each output must have been written with that checkpoint (its results.json names it); ``--any-checkpoint``
skips the check. It then prints the verdict's rows for the README's table ("Is the result right?"): per
setting or pair set, failures (more than 5 degrees off) flagged and trusted results right, for DIT alone and
DIT+ICP.
"""

import argparse
import json
import os
import sys

from dit_jax import checkpoint, evaluation, registration


def _counts(verdict: dict | None) -> tuple[str, str]:
    if not verdict:
        return "-", "-"
    flagged = f"{round(verdict['failures_caught'] * verdict['failures'])} of {verdict['failures']}" \
        if verdict["failures"] else "-"
    right = f"{round(verdict['passed_right'] * verdict['passed'])} of {verdict['passed']}" if verdict["passed"] else "-"
    return flagged, right


def readme_rows(name: str, results: dict) -> list[str]:
    """The README verdict table's rows of one output: | data | DIT flagged | DIT right | DIT+ICP flagged |
    DIT+ICP right |."""
    rows = []
    for pair_set, methods in results.get("pair_sets", {}).items():
        info = results["pair_set_info"][pair_set]
        cells = [c for m in (evaluation.METHOD_DIT, evaluation.METHOD_DIT_ICP)
                 for c in _counts(methods.get(m, {}).get("summary", {}).get("verdict"))]
        rows.append(f"| {name}, {info['pairs']} pairs {info['angle']:.0f} degrees apart | " + " | ".join(cells) + " |")
    for setting, methods in results.get("settings", {}).items():
        cells = [c for m in (evaluation.METHOD_DIT, evaluation.METHOD_DIT_ICP)
                 for c in _counts((methods.get(m) or {}).get("verdict"))]
        pairs = results["setting_info"][setting]["pairs"]
        rows.append(f"| {name}, {setting.replace('_', ' ')} ({pairs} pairs) | " + " | ".join(cells) + " |")
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("outputs", nargs="+", help="evaluate.py output directories (with results.json)")
    parser.add_argument("--any-checkpoint", action="store_true",
                        help="re-score outputs written with another checkpoint too")
    args = parser.parse_args()
    thresholds = {**registration.DEFAULT_MAX_DISAGREEMENT,
                  **(checkpoint.read_extra(args.checkpoint).get("verdict_max_disagreement") or {})}
    for out in args.outputs:
        path = os.path.join(out, "results.json")
        with open(path) as f:
            results = json.load(f)
        written_with = results.get("checkpoint")
        if not args.any_checkpoint and written_with and os.path.realpath(written_with) != os.path.realpath(
                args.checkpoint):
            print(f"rescore_verdict: {path} was written with {written_with}, not {args.checkpoint}; "
                  "--any-checkpoint to re-score it anyway", file=sys.stderr)
            return 2
        evaluation.rescore_agreement(results, thresholds)
        table = evaluation.markdown_tables(results) if "settings" in results else evaluation.scan_tables(results)
        # Written next to the old files and moved over them, so an interruption never leaves half a file.
        for name, text in (("results.json", json.dumps(results, indent=2)), ("results.md", table)):
            with open(os.path.join(out, name + ".tmp"), "w") as f:
                f.write(text)
        for name in ("results.json", "results.md"):
            os.replace(os.path.join(out, name + ".tmp"), os.path.join(out, name))
        print(f"{out}: re-scored at {thresholds}")
        print("\n".join(readme_rows(os.path.basename(os.path.normpath(out)), results)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
