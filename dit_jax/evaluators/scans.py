"""Evaluation on real scans with known poses (:mod:`dit_jax.data.scans`): DIT, DIT+ICP, the default pipeline and
the baselines on pairs of scans, in the users' path (:meth:`dit_jax.pipeline.registration.Registrar.register_pairs`)."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence

import numpy as np

from dit_jax.evaluators import baselines as baselines_lib
from dit_jax.evaluators import report
from dit_jax.evaluators.common import (
    METHOD_DIT,
    METHOD_DIT_ICP,
    METHOD_PIPELINE,
    RIGHT_DEG,
    SCAN_THRESHOLDS,
    Estimates,
    agreement_rule,
    fitness_rule,
    progress_bar,
    refinement_summary,
    rotation_error_deg,
    run_dit,
    verdict_summary,
)
from dit_jax.geometry import icp as icp_lib
from dit_jax.pipeline import sampling
from dit_jax.pipeline.result import VERDICT_LEVELS


def register_baseline(name: str, src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, seconds)`` of baseline ``name`` (:data:`dit_jax.evaluators.baselines.SCAN_BASELINES`) on one pair of scans
    in their own units (``tgt ~ src @ R.T + t``): every point, in the unit sphere a tuned baseline is tuned for
    (:func:`dit_jax.pipeline.sampling.normalise`), in the data's units for a recipe and the feature candidate."""
    started = time.perf_counter()
    if name == baselines_lib.FEATURE_CANDIDATE:
        from dit_jax.features import matching

        found = matching.register_both_ways(src, tgt)
        rotation, translation = found.kept if found is not None else (np.eye(3), np.zeros(3))
        return rotation, translation, time.perf_counter() - started
    if name in baselines_lib.RECIPES:
        rotation, translation = baselines_lib.RECIPES[name](src, tgt)
        return rotation, translation, time.perf_counter() - started
    src_n, tgt_n, src_centre, tgt_centre, scale = sampling.normalise(src, tgt, "shared")
    rotation, translation = baselines_lib.get(name)(src_n, tgt_n)
    rotation = np.asarray(rotation, np.float64)
    translation = sampling.to_caller_units(rotation, np.asarray(translation, np.float64), src_centre, tgt_centre, scale)
    return rotation, translation, time.perf_counter() - started


def is_right(row: dict, criterion: tuple[float, float] | None) -> bool:
    """Whether a row's estimate counts as right: within the data's ``criterion`` (degrees, distance), or within
    :data:`dit_jax.evaluators.common.RIGHT_DEG` where the data give none."""
    if not criterion:
        return bool(row["rot_err"] <= RIGHT_DEG)
    return bool(row["rot_err"] <= criterion[0] and row.get("trans_err", np.inf) <= criterion[1])


def benchmark_summary(rows: list[dict], criterion: tuple[float, float]) -> dict:
    """The 3DMatch benchmark's figures of one method's rows (each with ``rmse``, ``consecutive``, ``scene``):

    ``recall``: the share of non-consecutive pairs registered (RMSE at most
    :data:`dit_jax.data.scans.BENCHMARK_RMSE`), pooled; ``recall_scenes``: its mean over the scenes, as the
    benchmark averages; ``criterion_share``: the share of all pairs within ``criterion``; ``rre_median`` and
    ``rte_median``: median rotation (deg) and translation errors of the pairs within it; ``seconds_median``;
    and ``scenes``: each scene's own ``recall``, ``criterion_share`` and pair counts."""
    from dit_jax.data.scans import BENCHMARK_RMSE

    def figures(subset: list[dict]) -> dict:
        counted = [r for r in subset if not r["consecutive"]]
        right = [r for r in subset if is_right(r, criterion)]
        return {
            "pairs": len(subset),
            "counted": len(counted),
            "recall": float(np.mean([r["rmse"] <= BENCHMARK_RMSE for r in counted])) if counted else float("nan"),
            "criterion_share": float(np.mean([is_right(r, criterion) for r in subset])),
            "rre_median": float(np.median([r["rot_err"] for r in right])) if right else float("nan"),
            "rte_median": float(np.median([r["trans_err"] for r in right])) if right else float("nan"),
        }

    scenes = {scene: figures([r for r in rows if r["scene"] == scene]) for scene in sorted({r["scene"] for r in rows})}
    out = figures(rows) | {"seconds_median": float(np.median([r["seconds"] for r in rows])), "scenes": scenes}
    recalls = [s["recall"] for s in scenes.values() if not np.isnan(s["recall"])]
    out["recall_scenes"] = float(np.mean(recalls)) if recalls else float("nan")
    return out


def summarise_scans(rows: list[dict], criterion: tuple[float, float] | None = None) -> dict:
    """Median rotation error, shares within :data:`SCAN_THRESHOLDS`, median relative translation error and
    mean seconds of one method's rows (each with ``rot_err``, ``trans_err``, ``trans_err_rel``, ``seconds``);
    with a ``criterion`` (degrees, distance), also ``registered``: the pairs within both, as the data's
    benchmark counts them; where the rows carry the 3DMatch benchmark's ``rmse``, ``benchmark``
    (:func:`benchmark_summary`); where they carry the verdict's ``level``, ``levels``: for each level the pairs
    given it and how many of them were right (:func:`is_right`)."""
    rot = np.array([r["rot_err"] for r in rows])
    out = {
        "pairs": len(rows),
        "rot_median": float(np.median(rot)),
        "rot_mean": float(np.mean(rot)),
        "trans_rel_median": float(np.median([r["trans_err_rel"] for r in rows])),
        "seconds_per_pair": float(np.mean([r["seconds"] for r in rows])),
    }
    out.update({f"within_{t:g}": int(np.sum(rot <= t)) for t in SCAN_THRESHOLDS})
    if criterion is not None:
        out["registered"] = int(sum(is_right(r, criterion) for r in rows))
        if rows and "rmse" in rows[0]:
            out["benchmark"] = benchmark_summary(rows, criterion)
    if rows and "level" in rows[0]:
        out["levels"] = {
            level: {
                "pairs": sum(r["level"] == level for r in rows),
                "right": sum(r["level"] == level and is_right(r, criterion) for r in rows),
            }
            for level in VERDICT_LEVELS
        }
    return out


def sample_pairs(found, max_pairs: int | None, seed: int = 0) -> list:
    """At most ``max_pairs`` pairs of a :class:`dit_jax.data.scans.PairSet`: a series' first ones, a seeded
    sample of a benchmark's list (kept in the list's order)."""
    if max_pairs is None or len(found.pairs) <= max_pairs:
        return list(found.pairs)
    if found.kind != "gt.log":
        return list(found.pairs[:max_pairs])
    chosen = np.sort(np.random.default_rng(seed).choice(len(found.pairs), max_pairs, replace=False))
    return [found.pairs[k] for k in chosen]


def evaluate_scans(
    checkpoint_dir: str | None,
    scans_dir: str,
    out_dir: str,
    *,
    skips: Sequence[int] = (1, 2),
    baselines: Sequence[str] = (),
    max_pairs: int | None = None,
    progress: bool = True,
    inference: dict | None = None,
    worst_pairs: bool = True,
    seed: int = 0,
) -> dict:
    """DIT (and baselines) on pairs of real scans with known poses (:mod:`dit_jax.data.scans`).

    Pairs: the pair sets of :func:`dit_jax.data.scans.load_pair_sets` (a series gives scan i with scan i +
    ``skip`` for each skip: 1 adjacent, 2 every second one; a 3DMatch folder its gt.log lists, a folder of
    3DMatch scenes each list over every scene). ``max_pairs``: the first pairs of a series, a sample (seeded
    by ``seed``) of a benchmark's list. Writes
    ``results.md``, ``results.json`` (every pair's errors, the verdicts), ``success_ratio.png`` and
    ``worst_<pair set>.png`` (each method's worst pair) to ``out_dir``. Methods: DIT, DIT+ICP and the pipeline
    (one run of the pipeline, :func:`dit_jax.evaluators.common.run_dit`; ``inference``: changes to the
    checkpoint's settings, ``{"refine": "none"}`` drops DIT+ICP)
    and ``baselines`` (their tuned options for any setting). Errors: isotropic rotation error in degrees, and
    translation error over the target's bounding-box diagonal.
    """
    from dit_jax.data import scans as scans_lib
    from dit_jax.pipeline import registration

    if checkpoint_dir is None and not baselines:
        raise ValueError("nothing to evaluate: give a checkpoint or baselines")
    loaded = scans_lib.load_pair_sets(scans_dir, skips)
    registrar = registration.load(checkpoint_dir, **(inference or {})) if checkpoint_dir is not None else None
    pair_sets = {name: sample_pairs(found, max_pairs, seed) for name, found in loaded.items()}
    bar = progress_bar(
        progress, sum(map(len, pair_sets.values())) * (len(baselines) + bool(registrar)), "evaluate scans"
    )
    results = {
        "checkpoint": checkpoint_dir and os.path.abspath(checkpoint_dir),
        "scans": os.path.abspath(scans_dir),
        "pair_sets": {},
        "pair_set_info": {},
    }
    if registrar is not None:
        results["dit"] = _warm_up(registrar, pair_sets)
    for set_name, set_pairs in pair_sets.items():
        criterion = loaded[set_name].criterion
        results["pair_set_info"][set_name] = {
            "pairs": len(set_pairs),
            "angle": float(np.mean([rotation_error_deg(p.rotation, np.eye(3)) for p in set_pairs])),
            "kind": loaded[set_name].kind,
            "criterion": list(criterion) if criterion else None,
        }
        estimates = {}
        if registrar is not None:
            if bar is not None:
                bar.set_postfix_str(f"{set_name}: DIT")
            estimates = run_dit(registrar, [(p.source, p.target) for p in set_pairs], batch_size=1, bar=bar)
        for name in baselines:
            if bar is not None:
                bar.set_postfix_str(f"{set_name}: {name}")
            estimates[name] = _baseline_estimates(name, set_pairs, bar)
        done = results["pair_sets"][set_name] = _score_pair_set(estimates, set_pairs, criterion, registrar)
        if worst_pairs:
            title = f"worst pair of each method: {set_name} ({os.path.basename(os.path.normpath(scans_dir))})"
            _plot_worst(done, set_pairs, os.path.join(out_dir, f"worst_{set_name}.png"), title)
    if bar is not None:
        bar.close()
    table = report.scan_tables(results)
    report.write_results(out_dir, results, table)
    report.plot_scan_success(results, os.path.join(out_dir, "success_ratio.png"))
    results["table"] = table
    return results


def _warm_up(registrar, pair_sets: dict) -> dict:
    """Registers the first pair once, untimed, so that no pair's seconds include compiling the network (every
    scan is sampled to the same point count: one program serves them all); returns what DIT ran with."""
    first = next((pairs[0] for pairs in pair_sets.values() if pairs), None)
    if first is not None:
        registrar.register(first.source, first.target)
    return {
        "n_points": registrar.settings.n_points,
        "n_iters": registrar.config.n_iters,
        "inference_settings": registrar.settings.to_dict(),
    }


def _score_pair_set(estimates: dict[str, Estimates], pairs: Sequence, criterion, registrar) -> dict:
    """Each method's rows and summary on one pair set (``{method: {"summary", "rows"}}``): errors, the
    benchmark's ``criterion``, the verdict's precision and, for DIT+ICP, what the refinement changed."""
    done = {}
    for method, est in estimates.items():
        settings = registrar.settings if registrar is not None else None
        rows = [_pair_row(method, est, k, pair, settings) for k, pair in enumerate(pairs)]
        summary = summarise_scans(rows, criterion)
        if rows and "verdict" in rows[0]:
            summary["verdict"] = verdict_summary(
                np.array([r["rot_err"] for r in rows]),
                np.array([r["verdict"] for r in rows]),
                _rule_text(method, registrar.settings),
            )
        done[method] = {"summary": summary, "rows": rows}
    if METHOD_DIT_ICP in done:
        done[METHOD_DIT_ICP]["summary"]["refinement"] = refinement_summary(
            np.array([r["rot_err"] for r in done[METHOD_DIT]["rows"]]),
            np.array([r["rot_err"] for r in done[METHOD_DIT_ICP]["rows"]]),
            np.array([r["beats_truth"] for r in done[METHOD_DIT_ICP]["rows"]]),
        )
    return done


def _baseline_estimates(name: str, pairs: Sequence, bar) -> Estimates:
    """A baseline's :class:`Estimates` of scan pairs, each timed."""
    found = []
    for pair in pairs:
        found.append(register_baseline(name, pair.source, pair.target))
        if bar is not None:
            bar.update(1)
    rotation, translation, seconds = (np.array(a) for a in zip(*found))
    return Estimates(rotation, translation, seconds)


def _pair_row(method: str, est: Estimates, k: int, pair, settings) -> dict:
    """Pair ``k``'s row of a method: its errors, time and matrix; the benchmark's RMSE where the pair has its
    information matrix; DIT's rows add the verdict, judged by ``settings`` (the registrar's) where the
    pipeline's own is not recorded."""
    from dit_jax.data import scans as scans_lib

    rotation, translation = est.rotation[k], est.translation[k]
    extent = float(np.linalg.norm(np.ptp(pair.target, axis=0)))
    trans_err = float(np.linalg.norm(translation - pair.translation))
    row = {
        "pair": pair.name,
        "rot_err": rotation_error_deg(rotation, pair.rotation),
        "trans_err": trans_err,
        "trans_err_rel": trans_err / extent,
        "seconds": float(est.seconds[k]),
        "matrix": np.vstack([np.c_[rotation, translation], [0, 0, 0, 1]]).tolist(),
    }
    if method == METHOD_DIT_ICP:
        row["beats_truth"] = icp_lib.fits_better(
            pair.source, pair.target, (rotation, translation), (pair.rotation, pair.translation)
        )
    if pair.info is not None:
        row.update(
            rmse=scans_lib.benchmark_rmse(rotation, translation, pair), scene=pair.scene, consecutive=pair.consecutive
        )
    if est.candidate is not None:
        row["candidate"] = str(est.candidate[k])
    if est.level is not None:
        row["level"] = str(est.level[k])
    if est.fitness is not None:
        row["fitness"] = float(est.fitness[k])
        refine = "icp" if method == METHOD_DIT_ICP else "none"
        if est.verdict is not None:  # the pipeline's own, second candidate included
            row.update(verdict=bool(est.verdict[k]))
        elif est.agreement is not None:
            row.update(
                agreement=float(est.agreement[k]),
                verdict=bool(est.agreement[k] <= settings.max_disagreement(refine)),
            )
        else:
            row.update(verdict=bool(est.fitness[k] >= settings.min_fitness))
    return row


def _rule_text(method: str, settings) -> str:
    """The verdict rule a method's rows were judged by, in words, for the report."""
    refine = "icp" if method == METHOD_DIT_ICP else "none"
    rule = (
        agreement_rule(settings.max_disagreement(refine))
        if settings.verdict_rule == "agreement"
        else fitness_rule(settings.min_fitness)
    )
    if method == METHOD_PIPELINE:
        rule = (
            "on scans, local features both ways agree within "
            f"{settings.max_disagreement_features:g} deg and "
            f"{settings.max_offset_features:g} point spacings; elsewhere {rule}"
        )
    return rule


def _plot_worst(done: dict, pairs: Sequence, path: str, title: str) -> None:
    """Each method's worst pair of a pair set (the largest rotation error), drawn to ``path``."""
    by_name = {p.name: p for p in pairs}
    worst = []
    for method, r in done.items():
        row = max(r["rows"], key=lambda x: x["rot_err"])
        pair, matrix = by_name[row["pair"]], np.asarray(row["matrix"])
        worst.append(
            {
                "method": method,
                "pair": row["pair"],
                "src": pair.source,
                "tgt": pair.target,
                "R": matrix[:3, :3],
                "t": matrix[:3, 3],
                "truth": (pair.rotation, pair.translation),
            }
        )
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    report.plot_worst(path, title, worst)
