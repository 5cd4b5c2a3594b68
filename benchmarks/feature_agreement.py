"""How far apart the two directions of the registration by local features land, how strong a rival their
estimator kept and how well a turned twin of their motion fits, on right and wrong results: the evidence behind
the verdict's bounds on scans (InferenceSettings.max_disagreement_features, max_offset_features,
max_rival_features and max_twin_features).

    python benchmarks/feature_agreement.py ../shared/data/3dmatch ../shared/data/stanford_dragon_stand \\
        --max-pairs 0 --record docs/feature_agreement.jsonl

For each folder of scans with known poses and each of its pair sets (a seeded sample of --max-pairs per
benchmark list, the first pairs of a series): dit_jax.features.matching.register_both_ways as the pipeline calls
it; the kept direction (the larger overlap) is right by the data's criterion (3DMatch: the benchmark's RMSE
at most 0.2 m; otherwise within 5 degrees). For each pair of bounds (degrees, point spacings): how many results
the bounds trust, how many of those are right, and how many of the wrong ones they leave flagged, per pair
set and per scene, so a bound can be read with one scene left out; ``right_15`` counts right by the lists'
own criterion (15 degrees and 0.3 m) where the data have one. ``--max-pairs 0`` takes every pair;
``--pairs-out`` writes each pair's evidence (both directions' rival, twin, overlap and inliers too). Prints one
JSON record per pair set, then Markdown tables; ``--record`` writes the records to a file, which the verdict's
rival table in docs/verdict.md is generated from (python tools/results_page.py).

Calibration with a scene left out: over every pair of the benchmark lists at once, for each scene, the rival
and twin bounds of :data:`GRID` (at the settings' degrees and spacings) that trust the most right results of
the other scenes while at least :data:`PRECISION` of the results they trust there are right; then what those
bounds do on the scene left out (``left_out`` in the last record, and a table); ``all_scenes`` in that record:
the bounds the same rule chooses on every scene, the ones the settings ship.
"""

import argparse
import datetime
import json

import numpy as np

#: (degrees, point spacings, rival share, twin's share) bounds measured; inf is no bound.
BOUNDS = (
    *((d, s, np.inf, np.inf) for d, s in ((1.0, 2.0), (1.0, 3.0), (2.0, 4.0), (2.0, 6.0), (3.0, 8.0), (4.0, 12.0))),
    *((1.0, 2.0, r, np.inf) for r in (1.0, 0.6, 0.5, 0.4, 0.3)),
    *((1.0, 2.0, r, t) for r in (0.5, 0.4, 0.3) for t in (1.0, 0.9, 0.8, 0.7, 0.6)),
)
#: The (rival, twin) bounds the calibration with a scene left out chooses from, and the share of trusted results
#: that must be right on the scenes it calibrates on.
GRID = tuple((r, t) for r in (0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, np.inf) for t in (0.6, 0.7, 0.8, 0.9, 1.0, np.inf))
PRECISION = 0.99


def _trusted(row: dict, degrees: float, spacings: float, rival: float, twin: float) -> bool:
    return (
        row["disagreement"] <= degrees and row["offset"] <= spacings and row["rival"] <= rival and row["twin"] <= twin
    )


def _finite(row: dict) -> dict:
    """A pair row for JSON: inf as None (in lists too)."""

    def finite(v):
        if isinstance(v, list):
            return [finite(x) for x in v]
        return None if isinstance(v, float) and not np.isfinite(v) else v

    return {k: finite(v) for k, v in row.items()}


def _counts(subset: list[dict], degrees: float, spacings: float, rival: float, twin: float) -> dict:
    trusted = [r for r in subset if _trusted(r, degrees, spacings, rival, twin)]
    return {
        "trusted": len(trusted),
        "trusted_right": sum(r["right"] for r in trusted),
        "wrong": sum(not r["right"] for r in subset),
        "wrong_flagged": sum(not r["right"] and not _trusted(r, degrees, spacings, rival, twin) for r in subset),
    }


def calibrate(rows: list[dict], degrees: float, spacings: float) -> tuple[float, float, dict] | None:
    """The (rival, twin) bounds of :data:`GRID` that trust the most right results of ``rows`` while at least
    :data:`PRECISION` of those they trust are right (ties: the first, the stricter), with their counts; None
    where no bounds reach the precision."""
    best = None
    for rival, twin in GRID:
        c = _counts(rows, degrees, spacings, rival, twin)
        if c["trusted"] and c["trusted_right"] >= PRECISION * c["trusted"]:
            if best is None or c["trusted_right"] > best[2]["trusted_right"]:
                best = (rival, twin, c)
    return best


def _bound(value: float) -> float | None:
    return None if np.isinf(value) else value


def leave_one_scene_out(rows: list[dict], degrees: float, spacings: float) -> list[dict]:
    """For each scene of ``rows`` (pair rows of every list, each with its ``scene``): the bounds :func:`calibrate`
    chooses on the other scenes and the counts they give on that scene and on the others."""
    out = []
    for scene in sorted({r["scene"] for r in rows}):
        best = calibrate([r for r in rows if r["scene"] != scene], degrees, spacings)
        if best is None:
            continue
        rival, twin, on_calibration = best
        out.append(
            {
                "left_out": scene,
                "rival": _bound(rival),
                "twin": _bound(twin),
                "calibration": on_calibration,
                "held_out": _counts([r for r in rows if r["scene"] == scene], degrees, spacings, rival, twin),
            }
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    parser.add_argument("--max-pairs", type=int, default=40, help="per benchmark list; 0: every pair")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--record", default=None, help="also write the records to this file (JSON lines)")
    parser.add_argument("--pairs-out", default=None, help="also write one JSON line per pair (its evidence)")
    args = parser.parse_args()

    from dit_jax.data import scans as scans_lib
    from dit_jax.evaluators.scans import sample_pairs
    from dit_jax.features import matching
    from dit_jax.geometry import rigid

    records, benchmark_rows = [], []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            rows = []
            for pair in sample_pairs(found, args.max_pairs or None, args.seed):
                estimate = matching.register_both_ways(pair.source, pair.target, seed=args.seed)
                if estimate is None:
                    rows.append(
                        dict(scene=pair.scene, right=False, right_15=False, disagreement=np.inf, offset=np.inf)
                        | dict(rival=np.inf, twin=np.inf, seconds=0.0)
                    )
                    continue
                rotation, translation = estimate.kept
                degrees = rigid.rotation_angle_deg(rotation.T @ pair.rotation)
                if pair.info is not None:
                    rmse = scans_lib.benchmark_rmse(rotation, translation, pair)
                    right = bool(rmse <= scans_lib.BENCHMARK_RMSE)
                else:
                    right = bool(degrees <= 5.0)
                criterion = found.criterion or (5.0, np.inf)
                right_15 = degrees <= criterion[0] and np.linalg.norm(translation - pair.translation) <= criterion[1]
                rows.append(
                    dict(
                        scene=pair.scene,
                        right=right,
                        right_15=bool(right_15),
                        disagreement=estimate.disagreement,
                        offset=estimate.offset,
                        rival=max(estimate.rival),
                        twin=max(estimate.twin),
                        seconds=estimate.seconds,
                        # each direction's evidence, for rules that read it whole
                        rivals=[float(v) for v in estimate.rival],
                        twins=[float(v) for v in estimate.twin],
                        overlap=[float(v) for v in estimate.overlap],
                        inliers=[int(v) for v in estimate.inliers],
                    )
                )
            if found.kind == "gt.log":
                benchmark_rows += rows
            if args.pairs_out:
                with open(args.pairs_out, "a") as f:
                    f.writelines(json.dumps({"data": folder, "set": set_name, **_finite(row)}) + "\n" for row in rows)
            scenes = sorted({r["scene"] for r in rows})
            record = {
                "data": folder.rstrip("/").split("/")[-1],
                "set": set_name,
                "pairs": len(rows),
                "right": sum(r["right"] for r in rows),
                "median_s": float(np.median([r["seconds"] for r in rows])),
                "bounds": [],
                "date": datetime.date.today().isoformat(),
            }
            for degrees, spacings, rival, twin in BOUNDS:
                entry = {"degrees": degrees, "spacings": spacings}
                entry |= {"rival": None if np.isinf(rival) else rival, "twin": None if np.isinf(twin) else twin}
                for scene in [None, *scenes] if len(scenes) > 1 else [None]:
                    subset = [r for r in rows if scene is None or r["scene"] == scene]
                    trusted = [
                        r["disagreement"] <= degrees
                        and r["offset"] <= spacings
                        and r["rival"] <= rival
                        and r["twin"] <= twin
                        for r in subset
                    ]
                    counts = {
                        "trusted": int(sum(trusted)),
                        "trusted_right": int(sum(t and r["right"] for t, r in zip(trusted, subset))),
                        "trusted_right_15": int(sum(t and r["right_15"] for t, r in zip(trusted, subset))),
                        "wrong": int(sum(not r["right"] for r in subset)),
                        "wrong_flagged": int(sum(not t and not r["right"] for t, r in zip(trusted, subset))),
                    }
                    entry[scene or "all"] = counts
                record["bounds"].append(entry)
            records.append(record)
            print(json.dumps(record), flush=True)

    from dit_jax.pipeline.settings import InferenceSettings

    settings = InferenceSettings()
    left_out = (
        leave_one_scene_out(benchmark_rows, settings.max_disagreement_features, settings.max_offset_features)
        if benchmark_rows
        else []
    )
    if left_out:
        chosen = calibrate(benchmark_rows, settings.max_disagreement_features, settings.max_offset_features)
        on_all = {"rival": _bound(chosen[0]), "twin": _bound(chosen[1]), "counts": chosen[2]} if chosen else None
        records.append({"left_out": left_out, "all_scenes": on_all, "date": datetime.date.today().isoformat()})
        print(json.dumps(records[-1]), flush=True)
    if args.record:
        with open(args.record, "w") as f:
            f.writelines(json.dumps(record) + "\n" for record in records)
    print(
        "\n| data | set | pairs | right | bounds (deg, spacings, rival, twin) | trusted | of those right | wrong flagged |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for record in records:
        for entry in record.get("bounds", []):
            counts = entry["all"]
            print(
                f"| {record['data']} | {record['set']} | {record['pairs']} | {record['right']} | "
                f"{entry['degrees']:g}, {entry['spacings']:g}, {entry['rival'] or '-'}, {entry['twin'] or '-'} | "
                f"{counts['trusted']} | "
                f"{counts['trusted_right']} | {counts['wrong_flagged']} of {counts['wrong']} |"
            )

    if left_out:
        print(
            "\n| scene left out | bounds chosen (rival, twin) | others: trusted, right | left out: trusted, right | "
            "left out: wrong flagged |"
        )
        print("|---|---|---|---|---|")
        for e in left_out:
            c, h = e["calibration"], e["held_out"]
            print(
                f"| {e['left_out']} | {e['rival'] or '-'}, {e['twin'] or '-'} | {c['trusted']}, {c['trusted_right']} | "
                f"{h['trusted']}, {h['trusted_right']} | {h['wrong_flagged']} of {h['wrong']} |"
            )


if __name__ == "__main__":
    main()
