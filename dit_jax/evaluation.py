"""Evaluation: DIT and classical baselines on the same test pairs, the paper's tables and figures.

:func:`evaluate` is the job behind ``python evaluate.py``. For each data setting it makes the deterministic
test pairs (:mod:`dit_jax.data.pairs`), registers them with DIT (``register``, the model as it ships unless
overridden), with DIT refined by ICP (``DIT+ICP``, :mod:`dit_jax.icp`, as ``register(refine="icp")``) and with
the chosen Open3D baselines at their tuned options for that setting (:func:`dit_jax.baselines.tuned_options`),
and writes to ``out_dir``:

* ``results.md`` -- tables shaped like the paper's (RMSE / MAE of Euler angles and of translation), plus
  isotropic errors, RPM-Net's Chamfer distance, success ratio (the paper's criterion), the share within 5
  degrees and 0.05 (a criterion that independently sampled clouds can meet), the same share up to the
  shape's symmetry (a wrong pose that places the complete shape as closely as a 5-degree error counts as
  right: :func:`dit_jax.metrics.within_up_to_symmetry`) and time per pair;
* ``results.json`` -- every number, with per-category breakdowns and the success-ratio sweeps;
* ``success_ratio.png`` -- success ratio against a sweep of thresholds, one panel per setting;
* ``registrations.png`` -- a few pairs before and after DIT's registration;
* ``worst_<setting>.png`` -- each method's worst pair of each setting, before and after, so a reader sees
  how the methods fail.
"""

from __future__ import annotations

import json
import os
import sys
import time
from typing import Sequence

import jax.numpy as jnp
import numpy as np

from dit_jax import baselines as baselines_lib
from dit_jax import checkpoint, geometry, icp as icp_lib, metrics, model, plotting
from dit_jax.registration import DEFAULT_MAX_DISAGREEMENT, DEFAULT_MIN_FITNESS
from dit_jax.configs import GMCCE_THRESHOLDS
from dit_jax.data import pairs as pairs_lib
from dit_jax.data import shapes as shapes_lib

METHOD_DIT = "DIT"
METHOD_DIT_ICP = "DIT+ICP"
#: The rotation error that "within ... up to symmetry" (:func:`dit_jax.metrics.within_up_to_symmetry`) allows,
#: with the success curve's paired translation, 0.05.
SYMMETRY_DEGREES = 5.0


def predict_dit(params, config, dataset: pairs_lib.PairDataset, indices: np.ndarray, batch_size: int = 8,
                bar=None) -> dict[str, np.ndarray]:
    """DIT's estimates for pairs ``indices``: ``R`` (P, 3, 3), ``t`` (P, 3) and ``seconds`` per pair (the
    first batch, which compiles, is timed again after compiling). A short last batch is padded with repeats of
    its last pair, so one compiled program serves every batch and no compile lands in the timings."""
    rotations, translations, seconds, fitness = [], [], [], []
    for start in range(0, len(indices), batch_size):
        chunk = indices[start:start + batch_size]
        n_real = len(chunk)
        b = dataset.batch(np.concatenate([chunk, np.repeat(chunk[-1:], batch_size - n_real)]))
        src, tgt = jnp.asarray(b["src"]), jnp.asarray(b["tgt"])
        if start == 0:
            model.register(params, src, tgt, config)[0].block_until_ready()  # compile outside the timing
        t0 = time.perf_counter()
        rotation, translation, extras = model.register(params, src, tgt, config)
        rotation.block_until_ready()
        seconds.append(np.full(n_real, (time.perf_counter() - t0) / batch_size))
        fitness.append(np.asarray(extras["fitness"])[:n_real])
        rotations.append(np.asarray(rotation)[:n_real])
        translations.append(np.asarray(translation)[:n_real])
        if bar is not None:
            bar.update(n_real)
    return {"R": np.concatenate(rotations), "t": np.concatenate(translations), "seconds": np.concatenate(seconds),
            "fitness": np.concatenate(fitness)}


def verdict_summary(errors: np.ndarray, verdicts: np.ndarray, rule: str, right_deg: float = 5.0) -> dict:
    """How well a verdict separates results: errors (P,) in degrees, verdicts (P,) True = trusted; ``rule``
    says in words what it trusts (e.g. "agreement within 5.0 deg").

    ``failures_caught``: of the results more than ``right_deg`` off, the share flagged; ``passed_right``: of
    the results trusted, the share within ``right_deg`` (NaN where there are none)."""
    wrong = errors > right_deg
    caught = float(np.mean(~verdicts[wrong])) if wrong.any() else float("nan")
    right = float(np.mean(~wrong[verdicts])) if verdicts.any() else float("nan")
    return {"rule": rule, "failures": int(wrong.sum()), "failures_caught": caught, "passed": int(verdicts.sum()),
            "passed_right": right, "right_deg": right_deg}


def agreement_bands(errors: np.ndarray, agreement: np.ndarray, edges, right_deg: float = 5.0) -> list[list]:
    """How often results were right, band by band of the agreement verdict's evidence: errors (P,) and
    agreement (P,) in degrees; ``edges`` the bands' upper ends, increasing. Returns one ``[upper, pairs,
    right]`` per band (previous edge, edge], then ``[None, pairs, right]`` for those beyond the last edge:
    how many results fell in it and how many of them were within ``right_deg``. What
    :class:`dit_jax.registration.Result` quotes beside a verdict (``verdict_agreement_bands``)."""
    errors, agreement = np.asarray(errors, np.float64), np.asarray(agreement, np.float64)
    bands, low = [], -np.inf
    for high in [*edges, np.inf]:
        inside = (agreement > low) & (agreement <= high)
        bands.append([None if np.isinf(high) else float(high), int(inside.sum()),
                      int((inside & (errors <= right_deg)).sum())])
        low = high
    return bands


def verdict_line(name: str, v: dict) -> str:
    """One sentence on a :func:`verdict_summary` of method ``name``."""
    return (f"{name}'s verdict ({v['rule']}): flags {_share(v['failures_caught'])} of its {v['failures']} results "
            f"more than {v['right_deg']:g} deg off; of the {v['passed']} it trusts, {_share(v['passed_right'])} are "
            f"within {v['right_deg']:g} deg.")


def agreement_rule(max_disagreement: float) -> str:
    """The agreement verdict's rule in words (see :class:`dit_jax.registration.Registrar`)."""
    return f"target onto source agrees within {max_disagreement:g} deg"


def fitness_rule(min_fitness: float) -> str:
    """The fitness verdict's rule in words."""
    return f"fitness >= {min_fitness:.2f}"


def backward_agreement(params, config, dataset: pairs_lib.PairDataset, indices: np.ndarray, forward: dict,
                       refined: dict | None = None, batch_size: int = 8, bar=None) -> dict[str, dict]:
    """The agreement verdict's evidence, as ``register`` gathers it: each pair registered the other way
    (target onto source, and refined by ICP where ``refined``, DIT+ICP's estimates, is given). Returns
    ``{method: {"agreement": (P,) degrees between its rotation and the inverse of the backward one,
    "seconds": (P,) the backward work's time per pair}}``; DIT+ICP's entry also holds the refined backward
    motions, "R" (P, 3, 3) and "t" (P, 3) (target onto source), for :func:`choose_direction`."""
    swapped = pairs_lib.PairView(dataset, swap=True)
    back = predict_dit(params, config, swapped, indices, batch_size)
    out = {METHOD_DIT: {"agreement": np.array([geometry.rotation_angle_deg(r @ b)
                                               for r, b in zip(forward["R"], back["R"])]),
                        "seconds": back["seconds"]}}
    if refined is not None:
        back_refined = refine_dit(back, swapped, indices, truth_fit=False)  # its seconds include the network's
        out[METHOD_DIT_ICP] = {"agreement": np.array([geometry.rotation_angle_deg(r @ b)
                                                      for r, b in zip(refined["R"], back_refined["R"])]),
                               "seconds": back_refined["seconds"], "R": back_refined["R"], "t": back_refined["t"]}
    if bar is not None:
        bar.update(len(indices))
    return out


def refine_dit(dit: dict, dataset: pairs_lib.PairDataset, indices: np.ndarray, bar=None, *,
               truth_fit: bool = True) -> dict:
    """DIT's estimates (from :func:`predict_dit`) refined by ICP on the full clouds of each pair, as
    ``register(refine="icp")`` does; ``seconds`` counts both stages. ``beats_truth`` (P,) bool (with
    ``truth_fit``): the refined motion fits the clouds better than the true one
    (:func:`dit_jax.icp.fits_better`)."""
    rotations, translations, seconds, beats_truth = [], [], [], []
    for row, n in enumerate(indices):
        pair = dataset[int(n)]
        t0 = time.perf_counter()
        result = icp_lib.refine(pair["src"], pair["tgt"], dit["R"][row], dit["t"][row])
        seconds.append(dit["seconds"][row] + time.perf_counter() - t0)
        rotations.append(result.rotation)
        translations.append(result.translation)
        if truth_fit:
            beats_truth.append(icp_lib.fits_better(pair["src"], pair["tgt"], (result.rotation, result.translation),
                                                   (pair["R"], pair["t"])))
        if bar is not None:
            bar.update(1)
    return {"R": np.stack(rotations), "t": np.stack(translations), "seconds": np.asarray(seconds),
            "beats_truth": np.asarray(beats_truth)}


def choose_direction(refined: dict, backward: dict, dataset: pairs_lib.PairDataset, indices: np.ndarray) -> dict:
    """DIT+ICP as ``register(..., best_direction=True)`` gives it: per pair, whichever of the forward refined
    motion (``refined``, from :func:`refine_dit`) and the inverse of the refined backward one (``backward``,
    DIT+ICP's entry of :func:`backward_agreement`) lays the source onto the target better
    (:func:`dit_jax.icp.fits_better`). Its ``seconds`` count both directions' work, which the result now needs;
    ``backward`` (P,) bool marks the pairs where the backward motion was kept."""
    rotations, translations = np.array(refined["R"]), np.array(refined["t"])
    beats_truth, chosen = np.array(refined["beats_truth"]), np.zeros(len(indices), bool)
    for row, n in enumerate(indices):
        pair = dataset[int(n)]
        back_r, back_t = backward["R"][row], backward["t"][row]
        inverse = (back_r.T, -back_r.T @ back_t)
        if icp_lib.fits_better(pair["src"], pair["tgt"], inverse, (rotations[row], translations[row])):
            rotations[row], translations[row], chosen[row] = inverse[0], inverse[1], True
            if len(beats_truth):
                beats_truth[row] = icp_lib.fits_better(pair["src"], pair["tgt"], inverse, (pair["R"], pair["t"]))
    return {**refined, "R": rotations, "t": translations, "beats_truth": beats_truth, "backward": chosen,
            "seconds": np.asarray(refined["seconds"]) + np.asarray(backward["seconds"])}


def refinement_summary(before: np.ndarray, after: np.ndarray, beats_truth: np.ndarray | None = None,
                       good_deg: float = 10.0, goal_deg: float = 1.0) -> dict:
    """What ICP did to DIT's estimates: rotation errors (P,) in degrees before and after. Of the pairs DIT
    alone had within ``good_deg``, how many end within ``goal_deg`` (and the worst of them); the mean change
    over those pairs and over all. With ``beats_truth`` (P,) bool (the refined motion fits the clouds better
    than the truth), ``good_missed_data``: how many of the misses the data themselves place elsewhere, which
    no refinement that fits the points can bring within the goal."""
    good = before <= good_deg
    extra = {}
    if beats_truth is not None:
        extra["good_missed_data"] = int(np.sum(good & (after > goal_deg) & np.asarray(beats_truth, bool)))
    return extra | {"good_deg": good_deg, "goal_deg": goal_deg, "good": int(good.sum()),
            "good_within_goal": int(np.sum(after[good] <= goal_deg)),
            "good_worst_after": float(after[good].max()) if good.any() else float("nan"),
            "good_mean_before": float(before[good].mean()) if good.any() else float("nan"),
            "good_mean_after": float(after[good].mean()) if good.any() else float("nan"),
            "mean_before": float(before.mean()), "mean_after": float(after.mean()), "pairs": int(len(before))}


def refinement_line(r: dict) -> str:
    if not r["good"]:
        return (f"DIT+ICP: no pair had DIT alone within {r['good_deg']:g} deg; mean rotation error "
                f"{r['mean_before']:.3g} -> {r['mean_after']:.3g} deg over all {r['pairs']}.")
    return (f"DIT+ICP: of the {r['good']} pairs DIT alone had within {r['good_deg']:g} deg, {r['good_within_goal']} end "
            f"within {r['goal_deg']:g} deg (worst {r['good_worst_after']:.3g}; mean {r['good_mean_before']:.3g} -> "
            f"{r['good_mean_after']:.3g})" + _data_limited(r) + f"; over all {r['pairs']} pairs the mean goes {r['mean_before']:.3g} -> "
            f"{r['mean_after']:.3g} deg.")


def _data_limited(r: dict) -> str:
    missed = r["good"] - r["good_within_goal"]
    if "good_missed_data" not in r or not missed:
        return ""
    return (f"; of the {missed} that do not, {r['good_missed_data']} end where the clouds fit better than at the "
            "true pose (trimmed fit), so the data, not the refinement, place them there")


def predict_baseline(name: str, dataset: pairs_lib.PairDataset, indices: np.ndarray, bar=None,
                     setting: str | None = None):
    """A baseline's estimates for pairs ``indices``, as :func:`predict_dit`, with its options tuned for
    ``setting`` (:func:`dit_jax.baselines.tuned_options`)."""
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
    return {"R": np.stack(rotations), "t": np.stack(translations), "seconds": np.asarray(seconds)}


def complete_shapes(truth: dict) -> np.ndarray:
    """The complete, noise-free shape of each pair in its source frame, (B, P, 3), from a batch of
    :meth:`~dit_jax.data.pairs.PairDataset.batch` (whose ``tgt_clean`` holds it in the target frame)."""
    return np.einsum("bji,bnj->bni", truth["R"], truth["tgt_clean"] - truth["t"][:, None])


def score(pred: dict, dataset: pairs_lib.PairDataset, indices: np.ndarray, shape_names: Sequence[str],
          min_fitness: float | None = None, max_disagreement: float | None = None,
          symmetry_tolerance: np.ndarray | None = None) -> dict:
    """All metrics of one method's estimates (see :func:`dit_jax.metrics.summarise`), the RPM-Net Chamfer
    distance, the share within 5 degrees up to the shape's symmetry, time per pair, the per-category
    breakdown, the worst pair, each pair's rotation error, surface error and verdict evidence (``per_pair``)
    and, where ``pred`` carries that evidence (``fitness``, ``agreement``), how its verdicts do at
    ``min_fitness`` and ``max_disagreement``. ``symmetry_tolerance`` (P,): the pairs'
    :func:`dit_jax.metrics.symmetry_tolerance`, the same for every method (computed here when not given)."""
    truth = dataset.batch(indices)
    result = metrics.summarise(pred["R"], pred["t"], truth["R"], truth["t"])
    shapes = complete_shapes(truth)
    chamfer = []
    for start in range(0, len(indices), 16):
        sl = slice(start, start + 16)
        r, t = pred["R"][sl], pred["t"][sl]
        src_moved = np.einsum("bij,bnj->bni", r, truth["src"][sl]) + t[:, None]
        src_clean_moved = np.einsum("bij,bnj->bni", r, shapes[sl]) + t[:, None]
        chamfer.append(metrics.chamfer_distance(src_moved, truth["tgt"][sl], src_clean_moved, truth["tgt_clean"][sl]))
    result["chamfer"] = float(np.mean(np.concatenate(chamfer)))
    result["seconds_per_pair"] = float(np.mean(pred["seconds"]))
    errors = np.asarray(metrics.rotation_error_deg(jnp.asarray(pred["R"]), jnp.asarray(truth["R"])))
    surface = metrics.surface_error(shapes, pred["R"], pred["t"], truth["R"], truth["t"])
    if symmetry_tolerance is None:
        symmetry_tolerance = metrics.symmetry_tolerance(shapes, truth["R"], truth["t"], SYMMETRY_DEGREES)
    up_to_symmetry = metrics.within_up_to_symmetry(
        errors, np.linalg.norm(np.asarray(pred["t"], np.float64) - truth["t"], axis=-1), surface,
        symmetry_tolerance, SYMMETRY_DEGREES)
    result["within_up_to_symmetry"] = float(np.mean(up_to_symmetry))
    worst = int(np.argmax(errors))  # kept, so a later --reuse run can still draw this method's worst pair
    result["worst"] = {"pair": int(indices[worst]), "rot_err": float(errors[worst]),
                       "R": np.asarray(pred["R"][worst]).tolist(), "t": np.asarray(pred["t"][worst]).tolist()}
    # Per pair, so a verdict threshold chosen later can be scored on these pairs without registering them again.
    result["per_pair"] = {"pair": np.asarray(indices).tolist(), "rot_err": np.round(errors, 5).tolist(),
                          "surface_error": np.round(surface, 6).tolist(), "up_to_symmetry": up_to_symmetry.tolist()}
    for evidence in ("agreement", "fitness"):
        if evidence in pred:
            result["per_pair"][evidence] = np.round(np.asarray(pred[evidence], np.float64), 5).tolist()
    if "agreement" in pred and max_disagreement is not None:
        result["verdict"] = verdict_summary(errors, pred["agreement"] <= max_disagreement,
                                            agreement_rule(max_disagreement))
        result["verdict"]["extra_seconds_per_pair"] = float(np.mean(pred["agreement_seconds"]))
    if "fitness" in pred and min_fitness is not None:
        result["verdict_fitness"] = verdict_summary(errors, pred["fitness"] >= min_fitness, fitness_rule(min_fitness))
    by_category = {}
    for label in np.unique(truth["label"]):
        rows = truth["label"] == label
        name = shape_names[label] if 0 <= label < len(shape_names) else "uncategorised"
        s = metrics.summarise(pred["R"][rows], pred["t"][rows], truth["R"][rows], truth["t"][rows])
        by_category[name] = {k: s[k] for k in ("pairs", "rot_mae", "trans_mae", "rot_iso", "success")}
    result["by_category"] = by_category
    return result


def _share(x: float) -> str:
    return "-" if x != x else f"{100 * x:.1f} %"


def within(result: dict, degrees: float) -> float:
    """The share of pairs within ``degrees`` of rotation (and the paired translation threshold of the sweep:
    0.05 at 5 degrees), read from a method's success curve."""
    curve = result["success_curve"]
    return curve["ratio"][curve["rotation_thresholds"].index(degrees)]


def markdown_tables(results: dict) -> str:
    lines = []
    for setting, methods in results["settings"].items():
        info = results["setting_info"][setting]
        lines += [f"### {setting} ({info['pairs']} test pairs, {info['split']} split, GMCCE threshold "
                  f"{info['gmcce_threshold']})", "",
                  "| method | RMSE(R) deg | MAE(R) deg | RMSE(t) | MAE(t) | iso R deg | iso t | Chamfer | success "
                  "| within 5 deg, 0.05 | the same up to symmetry | s / pair |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, r in methods.items():
            lines.append(f"| {name} | {r['rot_rmse']:.4f} | {r['rot_mae']:.4f} | {r['trans_rmse']:.5f} | "
                         f"{r['trans_mae']:.5f} | {r['rot_iso']:.4f} | {r['trans_iso']:.5f} | {r['chamfer']:.6f} | "
                         f"{100 * r['success']:.1f} % | {100 * within(r, 5.0):.1f} % | "
                         f"{_share(r.get('within_up_to_symmetry', float('nan')))} | {r['seconds_per_pair']:.3f} |")
        if METHOD_DIT_ICP in methods and "refinement" in methods[METHOD_DIT_ICP]:
            lines += ["", refinement_line(methods[METHOD_DIT_ICP]["refinement"])]
        for name, r in methods.items():
            for key in ("verdict", "verdict_fitness"):
                if r.get(key):
                    lines += ["", verdict_line(name, r[key])]
                    if "backward_kept" in r and key == "verdict":
                        lines[-1] += (f" It keeps the better fitting of its two registrations (source onto target, "
                                      f"target onto source), the second on {r['backward_kept']} pairs; both are in "
                                      "its time per pair.")
                    elif "extra_seconds_per_pair" in r[key]:
                        lines[-1] += (f" Its second registration (target onto source) takes "
                                      f"{r[key]['extra_seconds_per_pair']:.3f} s per pair more.")
        lines.append("")
    return "\n".join(lines)


def plot_success(results: dict, path: str) -> None:
    plt = plotting.pyplot()

    settings = list(results["settings"])
    fig, axes = plt.subplots(1, len(settings), figsize=(5 * len(settings), 4), squeeze=False)
    for ax, setting in zip(axes[0], settings):
        for name, r in results["settings"][setting].items():
            curve = r["success_curve"]
            ax.plot(curve["rotation_thresholds"], curve["ratio"], marker="o", label=name)
        ticks = next(iter(results["settings"][setting].values()))["success_curve"]
        ax.set_xscale("log")
        ax.set_xticks(ticks["rotation_thresholds"])
        ax.set_xticklabels([f"{r:g}\u00b0\n{t:g}" for r, t in zip(ticks["rotation_thresholds"],
                                                                   ticks["translation_thresholds"])], fontsize=7)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("threshold: isotropic rotation (deg) and translation")
        ax.set_ylabel("success ratio")
        ax.set_title(setting)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_registrations(dataset: pairs_lib.PairDataset, pred: dict, indices: np.ndarray, path: str,
                       title: str) -> None:
    plt = plotting.pyplot()

    n = len(indices)
    fig = plt.figure(figsize=(8, 3.6 * n))
    for row, i in enumerate(indices):
        pair = dataset[int(i)]
        aligned = pair["src"] @ pred["R"][row].T + pred["t"][row]
        rot_err = float(metrics.rotation_error_deg(jnp.asarray(pred["R"][row]), jnp.asarray(pair["R"])))
        for col, (moving, label) in enumerate(((pair["src"], "source"), (aligned, "DIT-aligned source"))):
            ax = fig.add_subplot(n, 2, 2 * row + col + 1, projection="3d")
            ax.scatter(*pair["tgt"].T, s=1, c="tab:blue", label="target")
            ax.scatter(*moving.T, s=1, c="tab:red" if col == 0 else "tab:green", label=label)
            ax.set_title(f"pair {int(i)}: {'before' if col == 0 else f'after ({rot_err:.2f} deg error)'}",
                         fontsize=9)
            ax.set_axis_off()
            ax.legend(fontsize=7, loc="upper left", markerscale=5)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_worst(path: str, title: str, worst: Sequence[dict]) -> None:
    """One row per method: its worst pair, before and after its estimate, from two viewpoints
    (:func:`dit_jax.plotting.draw_registration`). ``worst``: dicts with ``method``, ``pair`` (a label),
    ``src`` (N, 3), ``tgt`` (M, 3), ``R``, ``t`` (the estimate) and ``truth`` ((R, t))."""
    plt = plotting.pyplot()
    fig = plt.figure(figsize=(13, 3.4 * len(worst)))
    panels = fig.subfigures(len(worst), 1, squeeze=False)[:, 0]
    for panel, w in zip(panels, worst):
        plotting.draw_registration(panel, 0, 1, w["src"], w["tgt"], w["R"], w["t"], w["method"])
        panel.suptitle(f"{w['method']}, pair {w['pair']}: " + plotting.describe(w["R"], w["t"], truth=w["truth"]),
                       fontsize=9)
    fig.suptitle(title, y=1.0 + 0.1 / len(worst))
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)


def plot_worst_pairs(dataset: pairs_lib.PairDataset, scored: dict, path: str, title: str) -> list[str]:
    """:func:`plot_worst` of each method's pair with the largest rotation error, from the ``worst`` entry of
    its scores (``{method: score(...)}``, reused ones included). Methods whose scores lack that entry (reused
    from a ``results.json`` written before it was kept) are left out and named in the title, so the picture
    never mixes in an earlier run's estimates. Returns the methods left out."""
    worst, missing = [], []
    for name, result in scored.items():
        if "worst" not in result:
            missing.append(name)
            continue
        pair = dataset[result["worst"]["pair"]]
        worst.append({"method": name, "pair": result["worst"]["pair"], "src": pair["src"], "tgt": pair["tgt"],
                      "R": np.asarray(result["worst"]["R"]), "t": np.asarray(result["worst"]["t"]),
                      "truth": (pair["R"], pair["t"])})
    if missing:
        title += f"\n(not shown: {', '.join(missing)}, reused without their worst pair; rerun them to draw it)"
    if worst:
        plot_worst(path, title, worst)
    return missing


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
    same = (old.get("data") == (data_dir or "embedded") and old.get("n_points") == n_points
            and info.get("split") == ("unseen" if unseen else "seen") and info.get("variant") == variant)
    if not same:
        raise ValueError(f"--reuse {reuse}: made on other pairs (data, split, variant or point count differ)")
    return old["settings"]


def evaluate(checkpoint_dir: str | None, out_dir: str, *, data_dir: str | None = None,
             settings: Sequence[str] = ("clean",), unseen: bool = False, variant: str = "authors",
             n_points: int | None = None, max_pairs: int | None = None, n_iters: int | None = None,
             gmcce_threshold: float | str | None = None, baselines: Sequence[str] = (), batch_size: int = 8,
             prepared_dir: str | None = None, progress: bool = True, compute_dtype: str = "float32",
             reuse: str | None = None, refine: bool = True, worst_pairs: bool = True, verdict: bool = True,
             best_direction: bool | None = None) -> dict:
    """Evaluates a model checkpoint (and baselines) on the test pairs of ``settings``; writes the outputs.

    Args:
      checkpoint_dir: a model checkpoint (:mod:`dit_jax.checkpoint`; ``WORKDIR/model`` of a training run, or
        converted authors' weights); None evaluates the baselines alone (no registrations figure then).
      n_points: points per shape; default what the checkpoint records for inference (``inference_points``),
        else its training point count, else 1000.
      max_pairs: evaluate only the first pairs of each setting (all by default).
      gmcce_threshold: None runs the model as it ships (its own inference settings, the same for every
        input); "authors" uses the authors' threshold for each setting (:data:`GMCCE_THRESHOLDS`); a number
        uses that threshold everywhere.
      compute_dtype: "bfloat16" runs PFT's products in bfloat16 (see :class:`dit_jax.configs.DITConfig`).
      reuse: an earlier output directory of this function: baselines it scored on the same pairs (same data,
        split, variant, point count and pair count) with the same options are taken from its ``results.json``
        instead of rerun.
      refine: add the ``DIT+ICP`` row.
      worst_pairs: draw each method's worst pair of each setting (``worst_<setting>.png``).
      verdict: also register every pair target onto source and report the agreement verdict (about doubles
        DIT's time; the fitness verdict is reported either way).
      best_direction: DIT+ICP keeps, per pair, the better fitting of its two directions, as ``register``'s
        ``best_direction`` (needs ``verdict`` and ``refine``); None:
        :data:`dit_jax.registration.DEFAULT_BEST_DIRECTION`.
    """
    from dit_jax.registration import DEFAULT_BEST_DIRECTION

    if best_direction and not (verdict and refine):
        raise ValueError("best_direction needs DIT+ICP and the verdict's second registration (refine and verdict)")
    if best_direction is None:
        best_direction = DEFAULT_BEST_DIRECTION and verdict and refine
    if checkpoint_dir is None and not baselines:
        raise ValueError("nothing to evaluate: give a checkpoint or baselines")
    if checkpoint_dir is not None:
        params, config = checkpoint.restore(checkpoint_dir)
        extra = checkpoint.read_extra(checkpoint_dir)
    else:
        params, config, extra = None, None, {}
    n_points = n_points or extra.get("inference_points") or extra.get("n_points") or 1000
    min_fitness = extra.get("verdict_min_fitness", DEFAULT_MIN_FITNESS)
    max_disagreement = {**DEFAULT_MAX_DISAGREEMENT, **(extra.get("verdict_max_disagreement") or {})}
    test_shapes = shapes_lib.load_shapes(data_dir, "test", data_dir=prepared_dir,
                                         n_points=pairs_lib.shape_points(data_dir, n_points, settings))
    os.makedirs(out_dir, exist_ok=True)
    results = {"checkpoint": checkpoint_dir and os.path.abspath(checkpoint_dir), "data": data_dir or "embedded",
               "n_points": n_points, "model_config": config and config.to_dict(), "compute_dtype": compute_dtype,
               "settings": {}, "setting_info": {}}
    bar = None
    datasets = {}
    for setting in settings:
        ds = pairs_lib.PairDataset(test_shapes, pairs_lib.PairConfig(setting=setting, unseen=unseen,
                                                                       variant=variant, n_points=n_points))
        datasets[setting] = (ds, np.arange(min(len(ds), max_pairs or len(ds))))
    if progress:
        from tqdm.auto import tqdm

        methods = len(baselines) + (params is not None) * (1 + verdict + refine)
        bar = tqdm(total=sum(len(ix) for _, ix in datasets.values()) * methods, desc="evaluate",
                   unit="pair", dynamic_ncols=True)
    earlier = _reusable(reuse, data_dir, unseen, variant, n_points)
    first_dit = None
    for setting, (ds, indices) in datasets.items():
        if gmcce_threshold is None:
            threshold = config.gmcce_threshold if config is not None else None
        elif gmcce_threshold == "authors":
            threshold = GMCCE_THRESHOLDS[setting]
        else:
            threshold = float(gmcce_threshold)
        preds = {}
        if params is not None:
            if bar is not None:
                bar.set_postfix_str(f"{setting}: DIT")
            run_config = config.replace(gmcce_threshold=threshold, n_iters=n_iters or config.n_iters,
                                        compute_dtype=compute_dtype)
            preds[METHOD_DIT] = predict_dit(params, run_config, ds, indices, batch_size, bar)
            if refine:
                if bar is not None:
                    bar.set_postfix_str(f"{setting}: DIT+ICP")
                preds[METHOD_DIT_ICP] = refine_dit(preds[METHOD_DIT], ds, indices, bar)
            if verdict:
                if bar is not None:
                    bar.set_postfix_str(f"{setting}: verdict (target onto source)")
                agreement = backward_agreement(params, run_config, ds, indices, preds[METHOD_DIT],
                                               preds.get(METHOD_DIT_ICP), batch_size, bar)
                for method, evidence in agreement.items():
                    preds[method].update(agreement=evidence["agreement"], agreement_seconds=evidence["seconds"])
                if best_direction and METHOD_DIT_ICP in agreement:
                    preds[METHOD_DIT_ICP] = choose_direction(preds[METHOD_DIT_ICP], agreement[METHOD_DIT_ICP], ds,
                                                            indices)
                    # Both directions are now part of DIT+ICP's own time; the verdict adds nothing to it.
                    preds[METHOD_DIT_ICP]["agreement_seconds"] = np.zeros(len(indices))
        reused = {}
        for name in baselines:
            old = earlier.get(setting, {}).get(name)
            options = baselines_lib.tuned_options(name, setting).to_dict()
            if old is not None and old["pairs"] == len(indices) and old.get("options") == options:
                reused[name] = old
                if bar is not None:
                    bar.update(len(indices))
                continue
            if bar is not None:
                bar.set_postfix_str(f"{setting}: {name}")
            preds[name] = predict_baseline(name, ds, indices, bar, setting)
        truth = ds.batch(indices)
        tolerance = (metrics.symmetry_tolerance(complete_shapes(truth), truth["R"], truth["t"], SYMMETRY_DEGREES)
                     if preds else None)
        scored = {name: score(p, ds, indices, test_shapes.shape_names, min_fitness,
                              max_disagreement["icp" if name == METHOD_DIT_ICP else "none"], tolerance)
                  for name, p in preds.items()}
        for name in baselines:
            if name in scored:
                scored[name]["options"] = baselines_lib.tuned_options(name, setting).to_dict()
        order = [m for m in (METHOD_DIT, METHOD_DIT_ICP) if m in scored] + list(baselines)
        if METHOD_DIT_ICP in scored:
            truth_r = jnp.asarray(truth["R"])
            errors = {m: np.asarray(metrics.rotation_error_deg(jnp.asarray(preds[m]["R"], jnp.float32), truth_r))
                      for m in (METHOD_DIT, METHOD_DIT_ICP)}
            scored[METHOD_DIT_ICP]["refinement"] = refinement_summary(errors[METHOD_DIT], errors[METHOD_DIT_ICP],
                                                                      preds[METHOD_DIT_ICP]["beats_truth"])
            if "backward" in preds[METHOD_DIT_ICP]:
                scored[METHOD_DIT_ICP]["backward_kept"] = int(np.sum(preds[METHOD_DIT_ICP]["backward"]))
        results["settings"][setting] = {name: scored.get(name) or reused[name] for name in order}
        results["setting_info"][setting] = {"pairs": int(len(indices)), "split": "unseen" if unseen else "seen",
                                            "variant": variant, "gmcce_threshold": threshold,
                                            "n_iters": n_iters or (config.n_iters if config else None)}
        if first_dit is None and METHOD_DIT in preds:
            first_dit = (setting, ds, preds[METHOD_DIT])
        if worst_pairs and preds:
            missing = plot_worst_pairs(ds, results["settings"][setting], os.path.join(out_dir, f"worst_{setting}.png"),
                                       f"worst pair of each method: {setting} ({results['data']}, "
                                       f"{'unseen' if unseen else 'seen'} split)")
            if missing:
                print(f"note: worst_{setting}.png leaves out {', '.join(missing)}: reused from results that did not "
                      f"keep their worst pair", file=sys.stderr)
    if bar is not None:
        bar.close()
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump(results, f, indent=2)
    table = markdown_tables(results)
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(table)
    plot_success(results, os.path.join(out_dir, "success_ratio.png"))
    if first_dit is not None:
        setting, ds, pred = first_dit
        shown = np.arange(min(3, len(pred["R"])))
        plot_registrations(ds, {k: v[shown] for k, v in pred.items()}, shown,
                           os.path.join(out_dir, "registrations.png"), f"DIT on {results['data']} ({setting})")
    results["table"] = table
    return results


# ------------------------------------------------------------------------------------------ real scans

#: Rotation thresholds (degrees) of the real-scan tables and curves.
SCAN_THRESHOLDS = (1.0, 2.0, 5.0, 10.0)


def _normalise_pair(src: np.ndarray, tgt: np.ndarray):
    """Both clouds moved by their shared centroid and scaled into the unit sphere, as DIT's API does:
    returns ``(src_n, tgt_n, centre, scale)``."""
    centre = np.concatenate([src, tgt]).mean(axis=0)
    scale = max(np.linalg.norm(src - centre, axis=1).max(), np.linalg.norm(tgt - centre, axis=1).max())
    return (src - centre) / scale, (tgt - centre) / scale, centre, scale


def register_scan_pair(method: str, src: np.ndarray, tgt: np.ndarray, registrar=None):
    """``(R, t, seconds)`` of one method on one pair of scans in their own units (``tgt ~ src @ R.T + t``).

    DIT is the user's path, :meth:`dit_jax.registration.Registrar.register` on the raw clouds (sampling
    included in the time); a baseline gets the same pair in the unit sphere it is tuned for, every point."""
    started = time.perf_counter()
    if method in (METHOD_DIT, METHOD_DIT_ICP):
        result = registrar.register(src, tgt, refine="icp" if method == METHOD_DIT_ICP else "none")
        return result.rotation, result.translation, time.perf_counter() - started, result
    src_n, tgt_n, centre, scale = _normalise_pair(src, tgt)
    rotation, translation = baselines_lib.get(method)(src_n, tgt_n)
    rotation = np.asarray(rotation, np.float64)
    translation = scale * np.asarray(translation, np.float64) + centre - rotation @ centre
    return rotation, translation, time.perf_counter() - started, None


def _rotation_error_deg(rotation: np.ndarray, truth: np.ndarray) -> float:
    return geometry.rotation_angle_deg(np.asarray(rotation, np.float64).T @ truth)


def summarise_scans(rows: list[dict]) -> dict:
    """Median rotation error, shares within :data:`SCAN_THRESHOLDS`, median relative translation error and
    mean seconds of one method's rows (each with ``rot_err``, ``trans_err_rel``, ``seconds``)."""
    rot = np.array([r["rot_err"] for r in rows])
    out = {"pairs": len(rows), "rot_median": float(np.median(rot)), "rot_mean": float(np.mean(rot)),
           "trans_rel_median": float(np.median([r["trans_err_rel"] for r in rows])),
           "seconds_per_pair": float(np.mean([r["seconds"] for r in rows]))}
    out.update({f"within_{t:g}": int(np.sum(rot <= t)) for t in SCAN_THRESHOLDS})
    return out


def scan_tables(results: dict) -> str:
    dit = results.get("dit")
    lines = [f"DIT sees {dit['n_points']} points of each scan (farthest-point sampled) and iterates "
             f"{dit['n_iters']} times.", ""] if dit else []
    for pair_set, methods in results["pair_sets"].items():
        info = results["pair_set_info"][pair_set]
        lines += [f"### {pair_set} ({info['pairs']} pairs, about {info['angle']:.0f} degrees apart)", "",
                  "| method | median rotation error (deg) | " + " | ".join(f"within {t:g} deg" for t in SCAN_THRESHOLDS)
                  + " | median translation error / extent | s / pair |",
                  "|---|---|" + "---|" * len(SCAN_THRESHOLDS) + "---|---|"]
        for name, r in methods.items():
            s = r["summary"]
            within = " | ".join(f"{s[f'within_{t:g}']} of {s['pairs']}" for t in SCAN_THRESHOLDS)
            lines.append(f"| {name} | {s['rot_median']:.2f} | {within} | {s['trans_rel_median']:.4f} | "
                         f"{s['seconds_per_pair']:.2f} |")
        if METHOD_DIT_ICP in methods:
            lines += ["", refinement_line(methods[METHOD_DIT_ICP]["summary"]["refinement"])]
        for name, r in methods.items():
            if r["summary"].get("verdict"):
                lines += ["", verdict_line(name, r["summary"]["verdict"])]
        lines.append("")
    return "\n".join(lines)


def plot_scan_success(results: dict, path: str) -> None:
    """Share of pairs within a rotation threshold against the threshold, one panel per pair set."""
    plt = plotting.pyplot()

    thresholds = np.logspace(-1, np.log10(180), 60)
    sets = list(results["pair_sets"])
    fig, axes = plt.subplots(1, len(sets), figsize=(5 * len(sets), 4), squeeze=False)
    for ax, pair_set in zip(axes[0], sets):
        for name, r in results["pair_sets"][pair_set].items():
            errors = np.array([row["rot_err"] for row in r["rows"]])
            ax.plot(thresholds, [(errors <= t).mean() for t in thresholds], label=name)
        ax.set_xscale("log")
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("rotation error threshold (deg)")
        ax.set_ylabel("share of pairs within")
        ax.set_title(f"{pair_set} ({results['pair_set_info'][pair_set]['angle']:.0f} deg apart)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def evaluate_scans(checkpoint_dir: str | None, scans_dir: str, out_dir: str, *, skips: Sequence[int] = (1, 2),
                   baselines: Sequence[str] = (), max_pairs: int | None = None, progress: bool = True,
                   registrar_options: dict | None = None, refine: bool = True, worst_pairs: bool = True) -> dict:
    """DIT (and baselines) on pairs of real range scans with known poses (:mod:`dit_jax.data.scans`).

    Pairs: scan i with scan i + ``skip`` for each skip (1: adjacent, 2: every second one). Writes
    ``results.md``, ``results.json`` (every pair's errors, the verdicts), ``success_ratio.png`` and
    ``worst_<pair set>.png`` (each method's worst pair) to ``out_dir``. Methods: DIT, DIT+ICP (with
    ``refine``) and ``baselines`` (their tuned options for any setting). Errors: isotropic rotation error in degrees, and translation error over the target's
    bounding-box diagonal.
    """
    from dit_jax import registration
    from dit_jax.data import scans as scans_lib

    if checkpoint_dir is None and not baselines:
        raise ValueError("nothing to evaluate: give a checkpoint or baselines")
    all_scans = scans_lib.load_scans(scans_dir)
    registrar = None
    methods = list(baselines)
    if checkpoint_dir is not None:
        registrar = registration.load(checkpoint_dir, **(registrar_options or {}))
        methods[:0] = [METHOD_DIT, METHOD_DIT_ICP] if refine else [METHOD_DIT]
    pair_sets = {f"skip{k}": scans_lib.scan_pairs(all_scans, k)[:max_pairs] for k in skips}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(map(len, pair_sets.values())) * len(methods), desc="evaluate scans", unit="pair",
                   dynamic_ncols=True)
    results = {"checkpoint": checkpoint_dir and os.path.abspath(checkpoint_dir), "scans": os.path.abspath(scans_dir),
               "pair_sets": {}, "pair_set_info": {}}
    if registrar is not None:
        results["dit"] = {"n_points": registrar.n_points, "n_iters": registrar.config.n_iters}
        first = pair_sets[next(iter(pair_sets))][0]
        registrar.register(first.source, first.target, refine="none")  # compile outside the timings
    for set_name, set_pairs in pair_sets.items():
        results["pair_set_info"][set_name] = {
            "pairs": len(set_pairs),
            "angle": float(np.mean([_rotation_error_deg(p.rotation, np.eye(3)) for p in set_pairs]))}
        results["pair_sets"][set_name] = {}
        for method in methods:
            rows = []
            for pair in set_pairs:
                if bar is not None:
                    bar.set_postfix_str(f"{set_name}: {method}")
                rotation, translation, seconds, result = register_scan_pair(method, pair.source, pair.target,
                                                                            registrar)
                extent = float(np.linalg.norm(np.ptp(pair.target, axis=0)))
                row = {"pair": pair.name, "rot_err": _rotation_error_deg(rotation, pair.rotation),
                       "trans_err_rel": float(np.linalg.norm(translation - pair.translation)) / extent,
                       "seconds": seconds, "matrix": np.vstack([np.c_[rotation, translation], [0, 0, 0, 1]]).tolist()}
                if method == METHOD_DIT_ICP:
                    row["beats_truth"] = icp_lib.fits_better(pair.source, pair.target, (rotation, translation),
                                                             (pair.rotation, pair.translation))
                if result is not None:
                    row.update(inlier_ratio=result.inlier_ratio, fitness=result.fitness)
                    if getattr(result, "verdict", None) is not None:
                        row.update(verdict=result.verdict, agreement=result.agreement)
                rows.append(row)
                if bar is not None:
                    bar.update(1)
            summary = summarise_scans(rows)
            if rows and "verdict" in rows[0]:
                rule = (agreement_rule(registrar.max_disagreement["icp" if method == METHOD_DIT_ICP else "none"])
                        if registrar.verdict_rule == "agreement" else fitness_rule(registrar.min_fitness))
                summary["verdict"] = verdict_summary(np.array([r["rot_err"] for r in rows]),
                                                     np.array([r["verdict"] for r in rows]), rule)
            results["pair_sets"][set_name][method] = {"summary": summary, "rows": rows}
        done = results["pair_sets"][set_name]
        if METHOD_DIT_ICP in done:
            done[METHOD_DIT_ICP]["summary"]["refinement"] = refinement_summary(
                np.array([r["rot_err"] for r in done[METHOD_DIT]["rows"]]),
                np.array([r["rot_err"] for r in done[METHOD_DIT_ICP]["rows"]]),
                np.array([r["beats_truth"] for r in done[METHOD_DIT_ICP]["rows"]]))
        if worst_pairs:
            by_name = {p.name: p for p in set_pairs}
            worst = []
            for method, r in results["pair_sets"][set_name].items():
                row = max(r["rows"], key=lambda x: x["rot_err"])
                pair, matrix = by_name[row["pair"]], np.asarray(row["matrix"])
                worst.append({"method": method, "pair": row["pair"], "src": pair.source, "tgt": pair.target,
                              "R": matrix[:3, :3], "t": matrix[:3, 3], "truth": (pair.rotation, pair.translation)})
            os.makedirs(out_dir, exist_ok=True)
            plot_worst(os.path.join(out_dir, f"worst_{set_name}.png"), f"worst pair of each method: {set_name} "
                       f"({os.path.basename(os.path.normpath(scans_dir))})", worst)
    if bar is not None:
        bar.close()
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump(results, f, indent=2)
    table = scan_tables(results)
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(table)
    plot_scan_success(results, os.path.join(out_dir, "success_ratio.png"))
    results["table"] = table
    return results


def rescore_agreement(results: dict, max_disagreement: dict) -> dict:
    """Re-scores the agreement verdict of an :func:`evaluate` or :func:`evaluate_scans` output (its
    ``results.json``) at new thresholds ({"none": degrees, "icp": degrees}), from the agreement each pair
    kept: nothing is registered again, and every other figure stays as measured. DIT's and DIT+ICP's verdict
    summaries (and, for scans, each row's ``verdict``) are replaced in place; returns ``results``.

    Raises ValueError where an agreement verdict was reported without its per-pair evidence (outputs written
    before 2026-11-28), which only a new evaluation can score."""
    def threshold(method: str) -> float:
        return float(max_disagreement["icp" if method == METHOD_DIT_ICP else "none"])

    for setting, methods in results.get("settings", {}).items():
        for method in (METHOD_DIT, METHOD_DIT_ICP):
            r = methods.get(method)
            if not r or not r.get("verdict"):
                continue
            if "agreement" not in r.get("per_pair", {}):
                raise ValueError(f"{setting}/{method}: no per-pair agreement kept; evaluate again to re-score it")
            errors, agreement = (np.asarray(r["per_pair"][k], float) for k in ("rot_err", "agreement"))
            extra = {k: v for k, v in r["verdict"].items() if k == "extra_seconds_per_pair"}
            r["verdict"] = verdict_summary(errors, agreement <= threshold(method),
                                           agreement_rule(threshold(method)), r["verdict"]["right_deg"]) | extra
    for pair_set, methods in results.get("pair_sets", {}).items():
        for method in (METHOD_DIT, METHOD_DIT_ICP):
            r = methods.get(method)
            verdict = r and r["summary"].get("verdict")
            if not verdict or not verdict["rule"].startswith("target onto source"):
                continue  # no verdict, or the fitness verdict, whose threshold this does not move
            for row in r["rows"]:
                row["verdict"] = bool(row["agreement"] <= threshold(method))
            r["summary"]["verdict"] = verdict_summary(
                np.array([row["rot_err"] for row in r["rows"]]), np.array([row["verdict"] for row in r["rows"]]),
                agreement_rule(threshold(method)), verdict["right_deg"])
    return results


# ------------------------------------------------------------------------------------------ rotation range


def angle_sweep(checkpoint_dir: str | None, out_dir: str, *, data_dir: str | None = None,
                setting: str = "independent_clean", unseen: bool = True, angles: Sequence[float] = tuple(range(0, 181, 15)),
                pairs_per_angle: int = 24, n_points: int | None = None, progress: bool = True,
                refine: bool = True) -> dict:
    """DIT's error against the rotation angle: test pairs of ``setting`` re-posed to rotations of exactly each
    angle about random axes (translations as drawn), with ``refine`` also DIT+ICP's as ``register(refine="icp")``
    returns it by default (both directions refined, the better fitting kept).
    Writes ``angle_sweep.md``, ``.json`` and ``.png``."""
    from dit_jax import registration

    points = {"n_points": n_points} if n_points else {}
    registrar = registration.load(checkpoint_dir, verdict_rule="fitness", **points)  # the network alone: one way
    as_users_get_it = registration.load(checkpoint_dir, **points) if refine else None
    test_shapes = shapes_lib.load_shapes(data_dir, "test",
                                         n_points=pairs_lib.shape_points(data_dir, registrar.n_points, [setting]))
    ds = pairs_lib.PairDataset(test_shapes, pairs_lib.PairConfig(setting=setting, unseen=unseen,
                                                                   n_points=registrar.n_points))
    # Pairs spread over the whole split (every category), the same ones for every angle.
    indices = np.linspace(0, len(ds) - 1, pairs_per_angle).astype(int)
    batch = ds.batch(indices)
    rng = np.random.default_rng(20261126)
    axes = rng.normal(size=(len(indices), 3))
    rows = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(angles) * len(indices), desc="angle sweep", unit="pair", dynamic_ncols=True)
    summary = lambda e: {"median": float(np.median(e)), "within_1": float(np.mean(e <= 1)),
                         "within_5": float(np.mean(e <= 5)), "within_10": float(np.mean(e <= 10)),
                         "errors": e.tolist()}
    for angle in angles:
        errors, refined = [], []
        for i in range(len(indices)):
            # Back to the shape's frame, then the new rotation; the translation stays as drawn.
            in_shape_frame = (batch["tgt"][i] - batch["t"][i]) @ batch["R"][i]
            rotation = geometry.axis_angle_matrix(axes[i], angle)
            moved = in_shape_frame @ rotation.T + batch["t"][i]
            alone = registrar.register(batch["src"][i], moved, refine="none")
            errors.append(_rotation_error_deg(alone.rotation, rotation))
            if refine:
                result = as_users_get_it.register(batch["src"][i], moved, refine="icp")
                refined.append(_rotation_error_deg(result.rotation, rotation))
            if bar is not None:
                bar.update(1)
        rows[float(angle)] = summary(np.asarray(errors))
        if refine:
            rows[float(angle)]["icp"] = summary(np.asarray(refined))
    if bar is not None:
        bar.close()
    results = {"checkpoint": checkpoint_dir and os.path.abspath(checkpoint_dir), "data": data_dir or "embedded",
               "setting": setting, "unseen": unseen, "pairs_per_angle": len(indices), "angles": rows}
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "angle_sweep.json"), "w") as f:
        json.dump(results, f, indent=2)
    lines = [f"DIT on {len(indices)} {setting} pairs ({'unseen' if unseen else 'seen'} split of "
             f"{results['data']}) per angle, random axes"
             + ("; DIT+ICP as `register` returns it (both directions refined, the better fitting kept)"
                if refine else ""), "",
             "| rotation (deg) | median error (deg) | within 5 deg | within 10 deg |"
             + (" DIT+ICP median | DIT+ICP within 1 deg | DIT+ICP within 5 deg |" if refine else ""),
             "|---|---|---|---|" + ("---|---|---|" if refine else "")]
    for a, r in rows.items():
        line = f"| {a:g} | {r['median']:.2f} | {100 * r['within_5']:.0f} % | {100 * r['within_10']:.0f} % |"
        if refine:
            line += f" {r['icp']['median']:.2f} | {100 * r['icp']['within_1']:.0f} % | {100 * r['icp']['within_5']:.0f} % |"
        lines.append(line)
    table = "\n".join(lines) + "\n"
    with open(os.path.join(out_dir, "angle_sweep.md"), "w") as f:
        f.write(table)
    plt = plotting.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    xs = list(rows)
    ax.plot(xs, [rows[a]["within_5"] for a in xs], marker="o", label="within 5 deg")
    ax.plot(xs, [rows[a]["within_10"] for a in xs], marker="o", label="within 10 deg")
    if refine:
        ax.plot(xs, [rows[a]["icp"]["within_1"] for a in xs], marker="s", ls="--", label="DIT+ICP within 1 deg")
        ax.plot(xs, [rows[a]["icp"]["within_5"] for a in xs], marker="s", ls="--", label="DIT+ICP within 5 deg")
    # Euler angles up to 45 degrees each: rotations up to 86 degrees, 90 % of them below 58.
    ax.axvspan(0, 58, color="tab:green", alpha=0.08, label="90 % of training rotations")
    ax.set_xlabel("rotation angle (deg)")
    ax.set_ylabel("share of pairs")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"DIT{' and DIT+ICP' if refine else ''} against rotation angle ({setting})", fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "angle_sweep.png"), dpi=110)
    plt.close(fig)
    results["table"] = table
    return results
