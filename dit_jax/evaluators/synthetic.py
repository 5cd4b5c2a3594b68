"""Evaluation on synthetic pairs: DIT and the classical baselines on the same test pairs of ModelNet40 or the
embedded set, in the paper's tables and figures (the job behind ``python evaluate.py``).

For each data setting, :func:`evaluate` makes the deterministic test pairs (:mod:`dit_jax.data.pairs`),
registers them through the registration pipeline (:mod:`dit_jax.pipeline.stages`, as users run it: rows ``DIT``, the
network's result, and ``DIT+ICP``, the refined one) and with the chosen baselines at their tuned options for
that setting (:func:`dit_jax.evaluators.baselines.tuned_options`), and writes to ``out_dir``:

* ``results.md``: tables shaped like the paper's (RMSE / MAE of Euler angles and of translation), plus
  isotropic errors, RPM-Net's Chamfer distance, success ratio (the paper's criterion), the share within 5
  degrees and 0.05, the same share up to the shape's symmetry (:func:`dit_jax.evaluators.metrics.within_up_to_symmetry`)
  and time per pair;
* ``results.json``: every number, with per-category breakdowns and the success-ratio sweeps;
* ``success_ratio.png``, ``registrations.png`` and ``worst_<setting>.png`` (each method's worst pair).
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from dit_jax.data import pairs as pairs_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.evaluators import baselines as baselines_lib
from dit_jax.evaluators import metrics, report
from dit_jax.evaluators.common import (
    METHOD_DIT,
    METHOD_DIT_ICP,
    METHOD_PIPELINE,
    Estimates,
    agreement_rule,
    fitness_rule,
    progress_bar,
    refinement_summary,
    run_dit,
    verdict_summary,
)
from dit_jax.geometry import icp as icp_lib
from dit_jax.network.configs import GMCCE_THRESHOLDS

#: The rotation error that "within ... up to symmetry" (:func:`dit_jax.evaluators.metrics.within_up_to_symmetry`) allows,
#: with the success curve's paired translation, 0.05.
SYMMETRY_DEGREES = 5.0


def predict_baseline(
    name: str, dataset: pairs_lib.PairDataset, indices: np.ndarray, bar=None, setting: str | None = None
):
    """A baseline's :class:`Estimates` of pairs ``indices`` of ``dataset``, with its options tuned for
    ``setting`` (:func:`dit_jax.evaluators.baselines.tuned_options`)."""
    method = baselines_lib.get(name, setting)
    rotations, translations, seconds = [], [], []
    for n in indices:
        pair = dataset[int(n)]
        t0 = time.perf_counter()
        rotation, translation = method(pair["src"], pair["tgt"])
        seconds.append(time.perf_counter() - t0)
        rotations.append(rotation)
        translations.append(translation)
        if bar is not None:
            bar.update(1)
    return Estimates(np.stack(rotations), np.stack(translations), np.asarray(seconds))


def complete_shapes(truth: dict) -> np.ndarray:
    """The complete, noise-free shape of each pair in its source frame, (B, P, 3), from a batch of
    :meth:`~dit_jax.data.pairs.PairDataset.batch` (whose ``tgt_clean`` holds it in the target frame)."""
    return np.einsum("bji,bnj->bni", truth["R"], truth["tgt_clean"] - truth["t"][:, None])


def score(
    pred: Estimates,
    dataset: pairs_lib.PairDataset,
    indices: np.ndarray,
    shape_names: Sequence[str],
    min_fitness: float | None = None,
    max_disagreement: float | None = None,
    symmetry_tolerance: np.ndarray | None = None,
) -> dict:
    """All metrics of one method's estimates (see :func:`dit_jax.evaluators.metrics.summarise`), the RPM-Net Chamfer
    distance, the share within 5 degrees up to the shape's symmetry, time per pair, the per-category
    breakdown, the worst pair, each pair's rotation error, surface error and verdict evidence (``per_pair``)
    and, where ``pred`` carries that evidence (``fitness``, ``agreement``), how its verdicts do at
    ``min_fitness`` and ``max_disagreement``. ``symmetry_tolerance`` (P,): the pairs'
    :func:`dit_jax.evaluators.metrics.symmetry_tolerance`, the same for every method (computed here when not given)."""
    truth = dataset.batch(indices)
    result = metrics.summarise(pred.rotation, pred.translation, truth["R"], truth["t"])
    shapes = complete_shapes(truth)
    chamfer = []
    for start in range(0, len(indices), 16):
        sl = slice(start, start + 16)
        r, t = pred.rotation[sl], pred.translation[sl]
        src_moved = np.einsum("bij,bnj->bni", r, truth["src"][sl]) + t[:, None]
        src_clean_moved = np.einsum("bij,bnj->bni", r, shapes[sl]) + t[:, None]
        chamfer.append(metrics.chamfer_distance(src_moved, truth["tgt"][sl], src_clean_moved, truth["tgt_clean"][sl]))
    result["chamfer"] = float(np.mean(np.concatenate(chamfer)))
    result["seconds_per_pair"] = float(np.mean(pred.seconds))
    errors = np.asarray(metrics.rotation_error_deg(jnp.asarray(pred.rotation), jnp.asarray(truth["R"])))
    surface = metrics.surface_error(shapes, pred.rotation, pred.translation, truth["R"], truth["t"])
    if symmetry_tolerance is None:
        symmetry_tolerance = metrics.symmetry_tolerance(shapes, truth["R"], truth["t"], SYMMETRY_DEGREES)
    up_to_symmetry = metrics.within_up_to_symmetry(
        errors,
        np.linalg.norm(np.asarray(pred.translation, np.float64) - truth["t"], axis=-1),
        surface,
        symmetry_tolerance,
        SYMMETRY_DEGREES,
    )
    result["within_up_to_symmetry"] = float(np.mean(up_to_symmetry))
    worst = int(np.argmax(errors))  # kept, so a later --reuse run can still draw this method's worst pair
    result["worst"] = {
        "pair": int(indices[worst]),
        "rot_err": float(errors[worst]),
        "R": np.asarray(pred.rotation[worst]).tolist(),
        "t": np.asarray(pred.translation[worst]).tolist(),
    }
    # Per pair, so a verdict threshold chosen later can be scored on these pairs without registering them again.
    result["per_pair"] = {
        "pair": np.asarray(indices).tolist(),
        "rot_err": np.round(errors, 5).tolist(),
        "surface_error": np.round(surface, 6).tolist(),
        "up_to_symmetry": up_to_symmetry.tolist(),
    }
    for evidence in ("agreement", "fitness"):
        if getattr(pred, evidence) is not None:
            result["per_pair"][evidence] = np.round(np.asarray(getattr(pred, evidence), np.float64), 5).tolist()
    if pred.verdict is not None:  # the pipeline's own verdict, its second candidate included
        result["verdict"] = verdict_summary(errors, pred.verdict, "the pipeline's own verdict")
        result["feature_candidate_kept"] = int(np.sum(pred.candidate == "features"))
        result["per_pair"]["verdict"] = np.asarray(pred.verdict, bool).tolist()
    elif pred.agreement is not None and max_disagreement is not None:
        result["verdict"] = verdict_summary(
            errors, pred.agreement <= max_disagreement, agreement_rule(max_disagreement)
        )
    if pred.fitness is not None and min_fitness is not None and pred.verdict is None:
        result["verdict_fitness"] = verdict_summary(errors, pred.fitness >= min_fitness, fitness_rule(min_fitness))
    by_category = {}
    for label in np.unique(truth["label"]):
        rows = truth["label"] == label
        name = shape_names[label] if 0 <= label < len(shape_names) else "uncategorised"
        s = metrics.summarise(pred.rotation[rows], pred.translation[rows], truth["R"][rows], truth["t"][rows])
        by_category[name] = {k: s[k] for k in ("pairs", "rot_mae", "trans_mae", "rot_iso", "success")}
    result["by_category"] = by_category
    return result


def _reusable(reuse: str | None, data_dir, unseen: bool, variant: str, n_points: int) -> dict:
    """The per-setting method scores of an earlier ``results.json`` made on the same pairs, else {}."""
    if not reuse:
        return {}
    path = os.path.join(reuse, "results.json")
    if not os.path.exists(path):
        raise ValueError(f"--reuse {reuse}: no results.json there")
    with open(path) as f:
        old = json.load(f)
    info = next(iter(old.get("setting_info", {}).values()), {})
    same = (
        old.get("data") == (data_dir or "embedded")
        and old.get("n_points") == n_points
        and info.get("split") == ("unseen" if unseen else "seen")
        and info.get("variant") == variant
    )
    if not same:
        raise ValueError(f"--reuse {reuse}: made on other pairs (data, split, variant or point count differ)")
    return old["settings"]


def evaluate(
    checkpoint_dir: str | None,
    out_dir: str,
    *,
    data_dir: str | None = None,
    settings: Sequence[str] = ("clean",),
    unseen: bool = False,
    variant: str = "authors",
    max_pairs: int | None = None,
    baselines: Sequence[str] = (),
    inference: dict | None = None,
    authors_thresholds: bool = False,
    batch_size: int = 8,
    prepared_dir: str | None = None,
    progress: bool = True,
    reuse: str | None = None,
    worst_pairs: bool = True,
) -> dict:
    """Evaluates a model checkpoint (and baselines) on the test pairs of ``settings``; writes the outputs.

    Args:
      checkpoint_dir: a model checkpoint (:mod:`dit_jax.network.checkpoint`); None evaluates the baselines alone.
      max_pairs: evaluate only the first pairs of each setting (all by default).
      inference: changes to the checkpoint's :class:`~dit_jax.pipeline.settings.InferenceSettings` (e.g.
        ``{"refine": "none"}`` drops the DIT+ICP row, ``{"verdict_rule": "fitness"}`` the second direction).
      authors_thresholds: run each setting at the authors' GMCCE threshold for it (:data:`GMCCE_THRESHOLDS`);
        else at the model's own, or ``inference``'s ``gmcce_threshold``, the same for every setting.
      reuse: an earlier output directory of this function: baselines it scored on the same pairs with the
        same options are taken from its ``results.json`` instead of rerun.
      worst_pairs: draw each method's worst pair of each setting (``worst_<setting>.png``).
    """
    if checkpoint_dir is None and not baselines:
        raise ValueError("nothing to evaluate: give a checkpoint or baselines")
    registrar = _registrar(checkpoint_dir, inference)
    n_points = registrar.settings.n_points if registrar else (inference or {}).get("n_points", 1000)
    shape_points = pairs_lib.shape_points(data_dir, n_points, settings)
    test_shapes = shapes_lib.load_shapes(
        data_dir, "test", data_dir=prepared_dir, progress=progress, n_points=shape_points
    )
    os.makedirs(out_dir, exist_ok=True)
    results = {
        "checkpoint": checkpoint_dir and os.path.abspath(checkpoint_dir),
        "data": data_dir or "embedded",
        "n_points": n_points,
        "model_config": registrar and registrar.config.to_dict(),
        "inference_settings": registrar and registrar.settings.to_dict(),
        "compute_dtype": registrar.config.compute_dtype if registrar else None,
        "settings": {},
        "setting_info": {},
    }
    datasets = {s: _test_pairs(test_shapes, s, unseen, variant, n_points, max_pairs) for s in settings}
    bar = progress_bar(
        progress, sum(len(ix) for _, ix in datasets.values()) * (len(baselines) + bool(registrar)), "evaluate"
    )
    earlier = _reusable(reuse, data_dir, unseen, variant, n_points)
    first_dit = None
    for setting, (ds, indices) in datasets.items():
        run = registrar
        if registrar is not None and authors_thresholds:
            run = registrar.replace(gmcce_threshold=GMCCE_THRESHOLDS[setting])
        preds = _dit_estimates(run, ds, indices, batch_size, bar, setting)
        reused = _run_baselines(baselines, setting, ds, indices, earlier.get(setting, {}), preds, bar)
        scored = _score_methods(preds, ds, indices, test_shapes.shape_names, registrar and registrar.settings)
        for name in baselines:
            if name in scored:
                scored[name]["options"] = _options(name, setting)
        order = [m for m in (METHOD_DIT, METHOD_DIT_ICP, METHOD_PIPELINE) if m in scored] + list(baselines)
        results["settings"][setting] = {name: scored.get(name) or reused[name] for name in order}
        results["setting_info"][setting] = _setting_info(len(indices), unseen, variant, registrar and run.config)
        if first_dit is None and METHOD_DIT in preds:
            first_dit = (setting, ds, preds[METHOD_DIT])
        if worst_pairs and preds:
            _plot_worst(ds, results, setting, unseen, out_dir)
    if bar is not None:
        bar.close()
    _write_outputs(results, first_dit, out_dir)
    return results


def _test_pairs(test_shapes, setting: str, unseen: bool, variant: str, n_points: int, max_pairs: int | None):
    """(the setting's test :class:`~dit_jax.data.pairs.PairDataset`, the indices of its first ``max_pairs``)."""
    config = pairs_lib.PairConfig(setting=setting, unseen=unseen, variant=variant, n_points=n_points)
    ds = pairs_lib.PairDataset(test_shapes, config)
    return ds, np.arange(min(len(ds), max_pairs or len(ds)))


def _setting_info(pairs: int, unseen: bool, variant: str, model_config) -> dict:
    """What a setting's rows were measured on: pairs, split, variant, and the network's GMCCE threshold and
    iterations (``model_config``: the config it ran, None without DIT)."""
    return {
        "pairs": int(pairs),
        "split": "unseen" if unseen else "seen",
        "variant": variant,
        "gmcce_threshold": model_config and model_config.gmcce_threshold,
        "n_iters": model_config and model_config.n_iters,
    }


def _run_baselines(baselines: Sequence[str], setting: str, ds, indices: np.ndarray, earlier: dict, preds: dict, bar):
    """Adds each baseline's :class:`Estimates` of the pairs ``indices`` of ``ds`` to ``preds``, except those
    ``earlier`` (the setting's scores in a reused ``results.json``) holds for the same pairs and options: those
    are returned, ``{name: scores}``, instead of being run again."""
    reused = {}
    for name in baselines:
        old = earlier.get(name)
        if old is not None and old["pairs"] == len(indices) and _same_options(old.get("options"), name, setting):
            reused[name] = old
            if bar is not None:
                bar.update(len(indices))
            continue
        if bar is not None:
            bar.set_postfix_str(f"{setting}: {name}")
        preds[name] = predict_baseline(name, ds, indices, bar, setting)
    return reused


def _registrar(checkpoint_dir: str | None, inference: dict | None):
    """The :class:`~dit_jax.pipeline.registration.Registrar` of a checkpoint with ``inference``'s changes to its
    settings; None without a checkpoint."""
    if checkpoint_dir is None:
        return None
    from dit_jax.pipeline import registration

    return registration.load(checkpoint_dir, **(inference or {}))


def _options(name: str, setting: str) -> dict:
    """A baseline's tuned options for ``setting``, as stored beside its scores."""
    return baselines_lib.tuned_options(name, setting).to_dict()


def _same_options(stored: dict | None, name: str, setting: str) -> bool:
    """Whether options ``stored`` beside earlier scores are those ``name`` runs with now for ``setting``; an
    option the record predates counts at its default, which the earlier run used."""
    try:
        return stored is not None and baselines_lib.Options.from_dict(stored).to_dict() == _options(name, setting)
    except TypeError:  # an option that no longer exists
        return False


def _dit_estimates(registrar, ds, indices: np.ndarray, batch_size: int, bar, setting: str) -> dict[str, Estimates]:
    """DIT's rows on pairs ``indices`` of ``ds`` (:func:`~dit_jax.evaluators.common.run_dit`); none without a
    registrar."""
    if registrar is None:
        return {}
    if bar is not None:
        bar.set_postfix_str(f"{setting}: DIT")
    pairs = [(ds[int(n)]["src"], ds[int(n)]["tgt"]) for n in indices]
    return run_dit(registrar, pairs, batch_size=batch_size, bar=bar)


def _score_methods(preds: dict[str, Estimates], ds, indices: np.ndarray, shape_names, inference_settings) -> dict:
    """Every method's :func:`score` on one setting's pairs; DIT's rows judged by the registrar's verdict
    thresholds, and the refined row with its :func:`refinement_summary`."""
    if not preds:
        return {}
    truth = ds.batch(indices)
    tolerance = metrics.symmetry_tolerance(complete_shapes(truth), truth["R"], truth["t"], SYMMETRY_DEGREES)
    scored = {}
    for name, pred in preds.items():
        verdict_options = {}
        if inference_settings is not None and name in (METHOD_DIT, METHOD_DIT_ICP, METHOD_PIPELINE):
            verdict_options = dict(
                min_fitness=inference_settings.min_fitness,
                max_disagreement=inference_settings.max_disagreement("icp" if name == METHOD_DIT_ICP else "none"),
            )
        scored[name] = score(pred, ds, indices, shape_names, symmetry_tolerance=tolerance, **verdict_options)
    if METHOD_DIT_ICP in scored:
        errors = {m: np.array(scored[m]["per_pair"]["rot_err"]) for m in (METHOD_DIT, METHOD_DIT_ICP)}
        refined = preds[METHOD_DIT_ICP]
        beats_truth = np.array(
            [
                icp_lib.fits_better(
                    ds[int(n)]["src"],
                    ds[int(n)]["tgt"],
                    (refined.rotation[k], refined.translation[k]),
                    (truth["R"][k], truth["t"][k]),
                )
                for k, n in enumerate(indices)
            ]
        )
        scored[METHOD_DIT_ICP]["refinement"] = refinement_summary(
            errors[METHOD_DIT], errors[METHOD_DIT_ICP], beats_truth
        )
        if refined.backward is not None:
            scored[METHOD_DIT_ICP]["backward_kept"] = int(np.sum(refined.backward))
    return scored


def _plot_worst(ds, results: dict, setting: str, unseen: bool, out_dir: str) -> None:
    """``worst_<setting>.png``: each method's worst pair of the setting."""
    missing = report.plot_worst_pairs(
        ds,
        results["settings"][setting],
        os.path.join(out_dir, f"worst_{setting}.png"),
        f"worst pair of each method: {setting} ({results['data']}, {'unseen' if unseen else 'seen'} split)",
    )
    if missing:
        print(
            f"note: worst_{setting}.png leaves out {', '.join(missing)}: reused from results that did not "
            f"keep their worst pair",
            file=sys.stderr,
        )


def _write_outputs(results: dict, first_dit: tuple | None, out_dir: str) -> None:
    """results.md and .json, success_ratio.png and (where DIT ran) registrations.png of its first setting's
    first three pairs; the tables go into ``results["table"]`` too."""
    table = report.markdown_tables(results)
    report.write_results(out_dir, results, table)
    report.plot_success(results, os.path.join(out_dir, "success_ratio.png"))
    if first_dit is not None:
        setting, ds, pred = first_dit
        shown = np.arange(min(3, len(pred.rotation)))
        report.plot_registrations(
            ds, pred, shown, os.path.join(out_dir, "registrations.png"), f"DIT on {results['data']} ({setting})"
        )
    results["table"] = table


def _with_settings(registrar, **changes):
    """A registrar sharing ``registrar``'s model, with changed inference settings."""
    return registrar.replace(**changes)
