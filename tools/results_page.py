"""The result tables of the README and docs/, generated from what evaluate.py wrote (docs/eval_*/results.json).

    python tools/results_page.py            # rewrites every generated table in place
    python tools/results_page.py --check    # exit status 1 where a committed table differs

Each table sits between ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->`` in its page, so the prose
around it is written by hand and the figures never are. Nothing is registered: the figures are those of the
results files, measured with the weights and settings each file records.

Tables:

* ``expect`` (README.md): one row per data set -- the real scans (objects, rooms, LiDAR) and ModelNet40's
  unseen categories per setting -- with DIT alone, DIT+ICP (the default) and the best baseline, and seconds
  per pair.
* ``results`` (docs/results.md): the same per evaluation directory, with every setting and pair set.
* ``rooms`` (docs/results.md): the 3DMatch benchmark's figures of the room scenes (``eval_3dmatch``), per list:
  registration recall (pooled and per scene), the share within 15 degrees and 0.3 m, median errors and
  seconds, and how often each level of the pipeline's verdict was right.
* ``rooms_full`` (docs/results.md and README.md): the default pipeline beside Open3D's room recipe on every
  pair of the 3DMatch scenes' lists, as benchmarks/register_scans.py measured them side by side
  (docs/rooms_full_lists.jsonl): the benchmark's recall, the share within the lists' criterion, seconds, how
  often exit 0 was right and how many wrong results were flagged.
* ``descriptors`` (docs/features.md): per 3DMatch scene and list, each descriptor's inlier ratio and
  feature-match recall, as benchmarks/descriptors.py measured them (docs/descriptors.jsonl).
* ``rooms_descriptors`` (docs/features.md): the default pipeline with each descriptor on every pair of the
  3DMatch scenes' lists (benchmarks/register_scans.py --descriptor, docs/rooms_descriptors_*.jsonl).
* ``descriptor_folds`` (docs/features.md): the learned descriptor with each scene left out of its training,
  on that scene, beside FPFH and the histograms (benchmarks/descriptor_folds.py, docs/descriptor_folds.jsonl).
* ``rival`` (docs/verdict.md): on scans, how many results the features' agreement trusts under each bound on
  the estimator's rival and on a turned twin's fit, and how many of those were right, as benchmarks/feature_agreement.py measured them
  (docs/feature_agreement.jsonl).
* ``bands`` (docs/verdict.md): the agreement bands the weights carry, from the validation pairs.
* ``scenes`` (docs/scenes.md): the 3DMatch scenes placed whole by ``dit_jax.scenes.scene`` (``eval_scenes``): per
  scene and list, the benchmark's pairs read off the scene beside the pairwise results, the fragments' pose
  errors, the edges and the seconds per fragment.
* ``levels`` (docs/verdict.md): how often each level of the verdict (:func:`dit_jax.pipeline.verdict.level`)
  was right, per setting and pair set, for DIT alone and DIT+ICP.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import sys

import numpy as np

from dit_jax.evaluators import baselines as baselines_lib
from dit_jax.evaluators import common
from dit_jax.evaluators import scans as scans_evaluator
from dit_jax.pipeline import verdict
from dit_jax.pipeline.result import VERDICT_LEVELS
from dit_jax.pipeline.settings import InferenceSettings
from dit_jax.pipeline.verdict import MIN_BAND_PAIRS

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
NETWORK = common.PIPELINE_METHODS
FEATURES = baselines_lib.FEATURE_CANDIDATE

#: The evaluation directories in docs/ the tables read, in the order they are shown, with a reader's name.
SOURCES = (
    ("eval_stanford_dragon", "Stanford Dragon range scans (object)"),
    ("eval_3dmatch", "3DMatch test scenes (rooms)"),
    ("eval_3dmatch_redkitchen", "3DMatch kitchen fragments (room)"),
    ("eval_lidar_pair", "LiDAR pair (street)"),
    ("eval_modelnet40_unseen", "ModelNet40, unseen categories"),
    ("eval_modelnet40_seen", "ModelNet40, seen categories"),
    ("eval_embedded", "embedded furniture set"),
)
#: Where each table lives.
PAGES = {
    "expect": ROOT / "README.md",
    "results": DOCS / "results.md",
    "rooms": DOCS / "results.md",
    "rooms_full": (DOCS / "results.md", ROOT / "README.md"),
    "descriptors": DOCS / "features.md",
    "rooms_descriptors": DOCS / "features.md",
    "descriptor_folds": DOCS / "features.md",
    "levels": DOCS / "verdict.md",
    "rival": DOCS / "verdict.md",
    "left_out": DOCS / "verdict.md",
    "bands": DOCS / "verdict.md",
    "scenes": DOCS / "scenes.md",
}
#: The README's table: the real sets and one synthetic directory.
EXPECT_SOURCES = ("eval_stanford_dragon", "eval_3dmatch", "eval_lidar_pair", "eval_modelnet40_unseen")
#: The rooms table's source: the 3DMatch benchmark's scenes.
ROOMS_SOURCE = "eval_3dmatch"
#: The records of benchmarks/feature_agreement.py: the features' verdict under each bound.
FEATURE_AGREEMENT = DOCS / "feature_agreement.jsonl"
#: The records of benchmarks/register_scans.py on the scenes' whole lists.
ROOMS_FULL = DOCS / "rooms_full_lists.jsonl"
#: The same with each descriptor (``--descriptor``), measured one after the other.
ROOMS_DESCRIPTORS = {name: DOCS / f"rooms_descriptors_{name}.jsonl" for name in ("fpfh", "histograms", "learned")}
#: How the rooms' descriptor table names each descriptor: the learned one registers each scene with the weights
#: trained with that scene left out.
DESCRIPTOR_LABELS = {"fpfh": "fpfh", "histograms": "histograms", "learned": "learned (its scene left out)"}
#: The records of benchmarks/descriptor_folds.py.
DESCRIPTOR_FOLDS = DOCS / "descriptor_folds.jsonl"
#: The records of benchmarks/descriptors.py.
DESCRIPTORS = DOCS / "descriptors.jsonl"


def _load(name: str) -> dict | None:
    path = DOCS / name / "results.json"
    return json.loads(path.read_text()) if path.exists() else None


def _scan_sets(results: dict) -> dict:
    return results.get("pair_sets", {})


def _scan_score(summary: dict) -> tuple[int, int]:
    """(right, pairs) of a pair set's summary: registered by its criterion where it has one, else within 5 deg."""
    return int(summary.get("registered", summary["within_5"])), int(summary["pairs"])


def _rows(name: str, results: dict) -> list[dict]:
    """One record per setting or pair set: ``label``, ``pairs``, and per method (score, seconds per pair),
    the score a share of pairs right; plus the best baseline's name."""
    rows = []
    if "pair_sets" in results:
        info = results.get("pair_set_info", {})
        for set_name, methods in _scan_sets(results).items():
            angle = info.get(set_name, {}).get("angle")
            label = set_name if angle is None else f"{set_name}, about {angle:.0f} deg apart"
            scores = {}
            for method, r in methods.items():
                right, pairs = _scan_score(r["summary"])
                scores[method] = (right / pairs, float(r["summary"]["seconds_per_pair"]), right, pairs)
            rows.append(
                {
                    "label": label,
                    "pairs": next(iter(scores.values()))[3],
                    "scores": scores,
                    "criterion": "registered"
                    if "registered" in next(iter(methods.values()))["summary"]
                    else "within 5 deg",
                }
            )
    else:
        for setting, methods in results.get("settings", {}).items():
            scores = {
                method: (common.success_share(s), float(s["seconds_per_pair"]), None, int(s["pairs"]))
                for method, s in methods.items()
            }
            rows.append(
                {
                    "label": setting,
                    "pairs": next(iter(scores.values()))[3],
                    "scores": scores,
                    "criterion": "within 5 deg",
                }
            )
    for row in rows:
        # The pipeline's own registration by local features is a stage of the default, not a baseline.
        baselines = [m for m in row["scores"] if m not in NETWORK and m != FEATURES]
        row["best"] = max(baselines, key=lambda m: (row["scores"][m][0], -row["scores"][m][1])) if baselines else None
    return rows


def _cell(row: dict, method: str | None) -> str:
    if method is None or method not in row["scores"]:
        return "-"
    share, _, right, pairs = row["scores"][method]
    return f"{right} of {pairs}" if right is not None else f"{100 * share:.0f} %"


def _seconds(row: dict, method: str | None) -> str:
    if method is None or method not in row["scores"]:
        return "-"
    return f"{row['scores'][method][1]:.2g}"


def _default(row: dict) -> str:
    """The row of the default pipeline: its own where the results have it, else DIT+ICP (results measured
    before the pipeline had a second candidate, or with it off)."""
    return common.METHOD_PIPELINE if common.METHOD_PIPELINE in row["scores"] else common.METHOD_DIT_ICP


def expect_table() -> list[str]:
    lines = [
        "| data | pairs | right by | DIT alone | DIT+ICP | default pipeline | best baseline | "
        "s / pair: default, baseline |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, title in SOURCES:
        if name not in EXPECT_SOURCES or (results := _load(name)) is None:
            continue
        for row in _rows(name, results):
            best = row["best"]
            baseline = f"{_cell(row, best)} ({best})" if best else "-"
            default = _default(row)
            lines.append(
                f"| {title}: {row['label']} | {row['pairs']} | {row['criterion']} | "
                f"{_cell(row, common.METHOD_DIT)} | {_cell(row, common.METHOD_DIT_ICP)} | "
                f"{_cell(row, common.METHOD_PIPELINE)} | {baseline} | "
                f"{_seconds(row, default)}, {_seconds(row, best)} |"
            )
    return lines


def results_tables() -> list[str]:
    lines = []
    for name, title in SOURCES:
        results = _load(name)
        if results is None:
            continue
        lines += [
            f"### {title}",
            "",
            f"Every method and column: [{name}/results.md]({name}/results.md); weights "
            f"`{pathlib.Path(results.get('checkpoint', '?')).name}`.",
            "",
            "| setting or pair set | pairs | right by | DIT alone | DIT+ICP | default pipeline | best baseline | "
            "s / pair: DIT, DIT+ICP, default, baseline |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for row in _rows(name, results):
            best = row["best"]
            lines.append(
                f"| {row['label']} | {row['pairs']} | {row['criterion']} | {_cell(row, common.METHOD_DIT)} | "
                f"{_cell(row, common.METHOD_DIT_ICP)} | {_cell(row, common.METHOD_PIPELINE)} | "
                f"{_cell(row, best)} ({best or 'none'}) | "
                f"{_seconds(row, common.METHOD_DIT)}, {_seconds(row, common.METHOD_DIT_ICP)}, "
                f"{_seconds(row, common.METHOD_PIPELINE)}, {_seconds(row, best)} |"
            )
        lines.append("")
    return lines[:-1]


def _settings_of(results: dict) -> InferenceSettings:
    recorded = results.get("inference_settings") or results.get("dit", {}).get("inference_settings")
    if recorded is None:
        from dit_jax.pipeline import registration

        return registration.load().settings
    return InferenceSettings(**recorded)


def level_counts(agreement, right, settings: InferenceSettings, refine: str, confirmed=None) -> dict:
    """{level: (results, right)} of results with these agreements (degrees), right or not. ``confirmed``: per
    result, whether the pipeline's second candidate confirmed it (trusted whatever the agreement)."""
    counts = {level: [0, 0] for level in VERDICT_LEVELS}
    threshold, bands = settings.max_disagreement(refine), settings.agreement_bands(refine)
    confirmed = [False] * len(agreement) if confirmed is None else confirmed
    for a, ok, sure in zip(agreement, right, confirmed):
        level = verdict.level(
            bool(sure) or a <= threshold, verdict.agreement_band(bands, a), settings.unconfirmed_min_right
        )
        counts[level][0] += 1
        counts[level][1] += int(ok)
    return {level: tuple(c) for level, c in counts.items()}


def levels_table() -> list[str]:
    header = " | ".join(f"{level}: results, right" for level in VERDICT_LEVELS)
    lines = [f"| data | method | {header} |", "|---|---|" + "---|" * len(VERDICT_LEVELS)]
    for name, title in SOURCES:
        results = _load(name)
        if results is None:
            continue
        settings = _settings_of(results)
        sets = []
        if "pair_sets" in results:
            info = results.get("pair_set_info", {})
            for set_name, methods in _scan_sets(results).items():
                criterion = info.get(set_name, {}).get("criterion")
                for method in NETWORK:
                    r = methods.get(method)
                    refined = methods.get(common.METHOD_DIT_ICP)
                    if method == common.METHOD_PIPELINE and r and "level" in r["rows"][0]:
                        # Its own level, as it reported it (the features' evidence on scans).
                        sets.append(
                            (
                                set_name,
                                method,
                                [row["level"] for row in r["rows"]],
                                [scans_evaluator.is_right(row, criterion) for row in r["rows"]],
                                "levels",
                            )
                        )
                    elif method == common.METHOD_PIPELINE and r and refined and "agreement" in refined["rows"][0]:
                        # Its level: trusted where it says so, else the level of DIT+ICP's own agreement.
                        sets.append(
                            (
                                set_name,
                                method,
                                [row["agreement"] for row in refined["rows"]],
                                [scans_evaluator.is_right(row, criterion) for row in r["rows"]],
                                [row["verdict"] for row in r["rows"]],
                            )
                        )
                    elif r and all(row.get("agreement") is not None for row in r["rows"]):
                        sets.append(
                            (
                                set_name,
                                method,
                                [row["agreement"] for row in r["rows"]],
                                [scans_evaluator.is_right(row, criterion) for row in r["rows"]],
                                None,
                            )
                        )
        else:
            for setting, methods in results.get("settings", {}).items():
                for method in NETWORK:
                    per_pair = (methods.get(method) or {}).get("per_pair", {})
                    if method == common.METHOD_PIPELINE and "verdict" not in per_pair:
                        continue  # measured before the pipeline kept its per-pair verdicts
                    if "agreement" in per_pair:
                        sets.append(
                            (
                                setting,
                                method,
                                per_pair["agreement"],
                                [e <= common.RIGHT_DEG for e in per_pair["rot_err"]],
                                per_pair.get("verdict"),
                            )
                        )
        for set_name, method, agreement, right, confirmed in sets:
            refine = "none" if method == common.METHOD_DIT else "icp"
            if isinstance(confirmed, str):  # "levels": each result's own level, in ``agreement``'s place
                counts = {
                    level: (
                        sum(a == level for a in agreement),
                        sum(a == level and ok for a, ok in zip(agreement, right)),
                    )
                    for level in VERDICT_LEVELS
                }
            else:
                counts = level_counts(np.asarray(agreement, float), right, settings, refine, confirmed)
            cells = " | ".join(f"{n}, {100 * ok / n:.0f} %" if n else "0" for n, ok in counts.values())
            lines.append(f"| {title}: {set_name} | {method} | {cells} |")
    return lines


def rooms_table() -> list[str]:
    """The benchmark's figures per list and method (:func:`dit_jax.evaluators.scans.benchmark_summary`), and
    the pipeline's levels with how often each was right."""
    from dit_jax.evaluators import report

    results = _load(ROOMS_SOURCE)
    if results is None:
        return ["(no 3DMatch evaluation in docs/eval_3dmatch yet)"]
    lines = []
    for set_name, methods in _scan_sets(results).items():
        info = results["pair_set_info"][set_name]
        lines += [
            f"**{set_name}** ({info['pairs']} pairs, about {info['angle']:.0f} deg apart on average)",
            "",
            *report.benchmark_table(methods, info["criterion"]),
            "",
        ]
        for method, r in methods.items():
            if r["summary"].get("levels"):
                lines += [report.levels_line(method, r["summary"]["levels"]), ""]
    return lines[:-1]


#: How the full-list table names the baseline each record was measured beside.
BASELINE_LABELS = {"open3d_room_5cm": "Open3D's tutorial recipe", "open3d_room_full": "Open3D at full strength"}


def _records(path: pathlib.Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []


def rooms_full_table() -> list[str]:
    """Per list of the 3DMatch scenes, every pair: the default pipeline beside the baseline it was measured
    with, from :data:`ROOMS_FULL`."""
    records = _records(ROOMS_FULL)
    if not records:
        return ["(no full-list measurement in docs/rooms_full_lists.jsonl yet)"]
    baseline = [m for m in records[0]["figures"] if m != "pipeline"][0]
    label = BASELINE_LABELS.get(baseline, baseline)
    lines = [
        f"| list | pairs | recall: default, {label} | within 15 deg and 0.3 m: default, {label} | s / pair: default, "
        f"{label} (median) | exit 0 right: by recall, by 15 deg / 0.3 m | wrong results flagged | right results "
        f"given exit 0 | probably wrong results wrong | registered by one only: default, {label} |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        ours, theirs = r["figures"]["pipeline"], r["figures"][baseline]
        verdict = r["verdict"]
        lines.append(
            f"| {r['set']} | {r['pairs']} | {100 * ours['recall']:.1f} %, {100 * theirs['recall']:.1f} % | "
            f"{100 * ours['criterion_share']:.1f} %, {100 * theirs['criterion_share']:.1f} % | "
            f"{ours['seconds_median']:.2f}, {theirs['seconds_median']:.2f} | "
            f"{_share(verdict['rmse']['exit_0'])}; {_share(verdict['criterion']['exit_0'])} | "
            f"{_share(verdict['rmse']['flagged'])} | {_share(_right_trusted(r))} | {_share(_flagged_wrong(r))} | "
            f"{len(r['only']['pipeline'])}, {len(r['only'][baseline])} |"
        )
    return lines


def _right_trusted(record: dict) -> list:
    """[right results, of them given exit 0], by the lists' criterion (15 degrees and 0.3 m)."""
    return [record["pipeline"]["registered"], record["verdict"]["criterion"]["exit_0"][1]]


def _flagged_wrong(record: dict) -> list:
    """[results called probably wrong, of them wrong], by the lists' criterion."""
    criterion = record["verdict"]["criterion"]
    return [record["pairs"] - criterion["exit_0"][0], criterion["flagged"][1]]


def _share(pair: list) -> str:
    return f"{pair[1]} of {pair[0]} ({100 * pair[1] / pair[0]:.0f} %)" if pair[0] else "none"


def rooms_descriptors_table() -> list[str]:
    """Per list of the 3DMatch scenes, every pair: the default pipeline with each descriptor
    (:data:`ROOMS_DESCRIPTORS`), its recall, share within 15 degrees and 0.3 m, seconds and verdict."""
    found = {name: {r["set"]: r for r in _records(path)} for name, path in ROOMS_DESCRIPTORS.items()}
    found = {name: records for name, records in found.items() if records or name == "fpfh"}
    if not all(found.values()):
        return ["(no measurement in docs/rooms_descriptors_*.jsonl yet)"]
    lines = [
        "| list | descriptor | recall | within 15 deg and 0.3 m | s / pair (median) | exit 0 right (by 15 deg / 0.3 m) "
        "| wrong results flagged |",
        "|---|---|---|---|---|---|---|",
    ]
    for set_name in found["fpfh"]:
        for name, records in found.items():
            r = records[set_name]
            figures, verdict = r["figures"]["pipeline"], r["verdict"]["criterion"]
            lines.append(
                f"| {set_name} | {DESCRIPTOR_LABELS[name]} | {100 * figures['recall']:.1f} % | {100 * figures['criterion_share']:.1f} % | "
                f"{figures['seconds_median']:.2f} | {_share(verdict['exit_0'])} | {_share(verdict['flagged'])} |"
            )
    return lines


def descriptors_table() -> list[str]:
    """Per scene and list of :data:`DESCRIPTORS`, each descriptor's mean inlier ratio and feature-match recall
    over the matches the estimator keeps, and the pairs of all scenes together."""
    records = _records(DESCRIPTORS)
    if not records:
        return ["(no measurement in docs/descriptors.jsonl yet)"]
    names = [n for n in ("fpfh", "fpfh_sqrt", "histograms") if n in records[0]]
    labels = {"fpfh": "FPFH (default)", "fpfh_sqrt": "FPFH, square-rooted", "histograms": "joined histograms"}
    lines = [
        "| scene | list | pairs | "
        + " | ".join(f"{labels[n]}: inlier ratio, FMR" for n in names)
        + " | histograms / FPFH |",
        "|---|---|---|" + "---|" * (len(names) + 1),
    ]

    def row(scene: str, group: list[dict]) -> str:
        pairs = sum(r["pairs"] for r in group)
        mean = {n: {k: sum(r[n][k] * r["pairs"] for r in group) / pairs for k in ("kept_inlier_ratio", "kept_fmr")}
                for n in names}  # fmt: skip
        cells = " | ".join(f"{mean[n]['kept_inlier_ratio']:.3f}, {100 * mean[n]['kept_fmr']:.0f} %" for n in names)
        gain = mean["histograms"]["kept_inlier_ratio"] / mean["fpfh"]["kept_inlier_ratio"]
        return f"| {scene} | {group[0]['set']} | {pairs} | {cells} | {gain:.2f}x |"

    for set_name in sorted({r["set"] for r in records}, key=lambda n: n != "3DMatch"):
        group = [r for r in records if r["set"] == set_name]
        lines += [row(r["scene"], [r]) for r in group] + [row("all three", group)]
    seconds = records[0]["seconds"]
    lines += [
        "",
        "Seconds a fragment: " + ", ".join(f"{labels[n]} {seconds[n]:.3f}" for n in names if n != "fpfh_sqrt"),
    ]
    return lines


def descriptor_folds_table() -> list[str]:
    """Per scene left out of the learned descriptor's training and list, the mean inlier ratio over all
    nearest-descriptor matches and over the ones the estimator keeps, of FPFH, the histograms and the learned
    descriptor (:data:`DESCRIPTOR_FOLDS`), and the three scenes summed."""
    records = _records(DESCRIPTOR_FOLDS)
    if not records:
        return ["(no measurement in docs/descriptor_folds.jsonl yet)"]
    names = ("fpfh", "histograms", "learned")
    lines = [
        "| left out | list | pairs | FPFH: all, kept | histograms: all, kept | learned: all, kept "
        "| learned / FPFH (all) | learned / histograms (all) |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def row(scene: str, listed: str, pairs: int, figures: dict) -> str:
        cells = " | ".join(f"{figures[n]['inlier_ratio']:.3f}, {figures[n]['kept_inlier_ratio']:.3f}" for n in names)
        ratio = lambda a, b: figures[a]["inlier_ratio"] / figures[b]["inlier_ratio"]  # noqa: E731
        return f"| {scene} | {listed} | {pairs} | {cells} | {ratio('learned', 'fpfh'):.2f}x | {ratio('learned', 'histograms'):.2f}x |"

    folds = [r for r in records if r["scene"] != "all"]
    for listed in sorted({r["set"] for r in folds}, key=lambda n: n != "3DMatch"):
        lines += [row(r["scene"], listed, r["pairs"], r) for r in folds if r["set"] == listed]
        total = next(r for r in records if r["scene"] == "all")["summed"][listed]
        lines.append(row("all three", listed, total["pairs"], total))
    seconds = sorted({r["scene"]: r["train_seconds"] for r in folds}.items())
    lines += ["", "Training seconds per fold: " + ", ".join(f"{scene} left out {s:.0f}" for scene, s in seconds)]
    return lines


def rival_table() -> list[str]:
    """Per pair set of :data:`FEATURE_AGREEMENT`, each bound on the rival and then on the turned twin (at the
    settings' degrees and spacings): results trusted, right by the data's own measure and by the lists'
    criterion, wrong flagged."""
    if not FEATURE_AGREEMENT.exists():
        return ["(no measurement in docs/feature_agreement.jsonl yet)"]
    settings = InferenceSettings()
    records = [json.loads(line) for line in FEATURE_AGREEMENT.read_text().splitlines() if line.strip()]
    lines = [
        "| data | pairs | rival bound | twin bound | trusted | right | right by 15 deg and 0.3 m | wrong flagged |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        for entry in r.get("bounds", []):
            if (entry["degrees"], entry["spacings"]) != (
                settings.max_disagreement_features,
                settings.max_offset_features,
            ):
                continue
            c = entry["all"]
            rival, twin = (("none" if entry.get(k) is None else f"{entry[k]:g}") for k in ("rival", "twin"))
            if (entry["rival"], entry.get("twin")) == (settings.max_rival_features, settings.max_twin_features):
                rival, twin = f"**{rival}**", f"**{twin}** (default)"
            right = f"{c['trusted_right']} ({100 * c['trusted_right'] / c['trusted']:.1f} %)" if c["trusted"] else "-"
            right_15 = "-" if r["data"] != "3dmatch" else f"{c['trusted_right_15']}"
            lines.append(
                f"| {r['data']} {r['set']} | {r['pairs']} | {rival} | {twin} | {c['trusted']} | {right} | {right_15} | "
                f"{c['wrong_flagged']} of {c['wrong']} |"
            )
    return lines


def left_out_table() -> list[str]:
    """The verdict's rival and twin bounds chosen with each 3DMatch scene left out (:data:`FEATURE_AGREEMENT`'s
    ``left_out`` record), and what they do on that scene."""
    records = []
    if FEATURE_AGREEMENT.exists():
        records = [json.loads(line) for line in FEATURE_AGREEMENT.read_text().splitlines() if line.strip()]
    found = [r["left_out"] for r in records if "left_out" in r]
    if not found:
        return ["(no calibration with a scene left out in docs/feature_agreement.jsonl yet)"]
    lines = [
        "| scene left out | bounds chosen on the others (rival, twin) | the others: trusted, right | left out: "
        "trusted, right | left out: wrong flagged |",
        "|---|---|---|---|---|",
    ]
    for e in found[0]:
        c, h = e["calibration"], e["held_out"]
        share = f" ({100 * h['trusted_right'] / h['trusted']:.0f} %)" if h["trusted"] else ""
        lines.append(
            f"| {e['left_out']} | {e['rival'] or 'none'}, {e['twin'] or 'none'} | {c['trusted']}, {c['trusted_right']} "
            f"| {h['trusted']}, {h['trusted_right']}{share} | {h['wrong_flagged']} of {h['wrong']} |"
        )
    return lines


def bands_table(source: str = "eval_modelnet40_unseen") -> list[str]:
    """The agreement bands the weights carry (as recorded with ``source``'s results): per band of agreement,
    how many validation results fell in it and the share of them within 5 degrees."""
    settings = _settings_of(_load(source) or {})
    lines = []
    for method, refine in ((common.METHOD_DIT, "none"), (common.METHOD_DIT_ICP, "icp")):
        bands = settings.agreement_bands(refine) or ()
        edges, low = [], 0.0
        for high, pairs, right in bands:
            label = f"{low:g}-{high:g}" if high is not None else f"beyond {low:g}"
            edges.append((label, int(pairs), int(right)))
            low = high
        if not lines:
            lines = [
                "| agreement (deg) | " + " | ".join(label for label, _, _ in edges) + " |",
                "|---|" + "---|" * len(edges),
            ]
        lines.append(f"| {method}: validation results | " + " | ".join(str(p) for _, p, _ in edges) + " |")
        lines.append(
            f"| {method}: within 5 deg | "
            + " | ".join(f"{100 * r / p:.0f} %" if p >= MIN_BAND_PAIRS else f"({r} of {p})" for _, p, r in edges)
            + " |"
        )
    return lines


def scenes_table() -> list[str]:
    """The 3DMatch scenes placed whole (``eval_scenes``), as :func:`dit_jax.evaluators.scenes.table` writes them."""
    from dit_jax.evaluators import scenes

    results = _load("eval_scenes")
    if results is None:
        return ["(no docs/eval_scenes/results.json yet)"]
    return scenes.table(results["scenes"]).splitlines()


TABLES = {
    "scenes": scenes_table,
    "expect": expect_table,
    "results": results_tables,
    "rooms": rooms_table,
    "rooms_full": rooms_full_table,
    "descriptors": descriptors_table,
    "rooms_descriptors": rooms_descriptors_table,
    "descriptor_folds": descriptor_folds_table,
    "rival": rival_table,
    "left_out": left_out_table,
    "levels": levels_table,
    "bands": bands_table,
}


def _replace(text: str, name: str, table: list[str]) -> str:
    pattern = re.compile(rf"(<!-- results:{name} -->\n).*?(<!-- /results:{name} -->)", re.S)
    if not pattern.search(text):
        raise ValueError(f"no <!-- results:{name} --> ... <!-- /results:{name} --> in the page")
    return pattern.sub(lambda m: m.group(1) + "\n".join(table) + "\n" + m.group(2), text)


def _pages(name: str) -> tuple[pathlib.Path, ...]:
    return PAGES[name] if isinstance(PAGES[name], tuple) else (PAGES[name],)


def render(name: str, page_path: pathlib.Path | None = None) -> tuple[str, str]:
    """(the page's text now, the page's text with table ``name`` regenerated); ``page_path``: which of the
    table's pages (default: its first)."""
    page = (page_path or _pages(name)[0]).read_text()
    return page, _replace(page, name, TABLES[name]())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 where a table differs")
    args = parser.parse_args(argv)
    stale = []
    for name in TABLES:
        for path in _pages(name):
            now, generated = render(name, path)
            if now != generated:
                stale.append(f"{path.relative_to(ROOT)} ({name})")
                if not args.check:
                    path.write_text(generated)
    if args.check and stale:
        print("stale tables: " + ", ".join(stale) + "; run python tools/results_page.py", file=sys.stderr)
        return 1
    print(("updated: " if stale else "up to date: ") + (", ".join(stale) or ", ".join(TABLES)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
