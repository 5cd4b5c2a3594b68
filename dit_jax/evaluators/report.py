"""Reports of evaluations: Markdown tables, the sentences beside them and the plots."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from dit_jax.data import pairs as pairs_lib
from dit_jax.evaluators import metrics
from dit_jax.evaluators.common import METHOD_DIT_ICP, RIGHT_DEG, SCAN_THRESHOLDS, success_share
from dit_jax.pictures import plotting


def verdict_line(name: str, v: dict) -> str:
    """One sentence on a :func:`verdict_summary` of method ``name``."""
    return (
        f"{name}'s verdict ({v['rule']}): flags {_share(v['failures_caught'])} of its {v['failures']} results "
        f"more than {v['right_deg']:g} deg off; of the {v['passed']} it trusts, {_share(v['passed_right'])} are "
        f"within {v['right_deg']:g} deg."
    )


def refinement_line(r: dict) -> str:
    if not r["good"]:
        return (
            f"DIT+ICP: no pair had DIT alone within {r['good_deg']:g} deg; mean rotation error "
            f"{r['mean_before']:.3g} -> {r['mean_after']:.3g} deg over all {r['pairs']}."
        )
    return (
        f"DIT+ICP: of the {r['good']} pairs DIT alone had within {r['good_deg']:g} deg, {r['good_within_goal']} end "
        f"within {r['goal_deg']:g} deg (worst {r['good_worst_after']:.3g}; mean {r['good_mean_before']:.3g} -> "
        f"{r['good_mean_after']:.3g})"
        + _data_limited(r)
        + f"; over all {r['pairs']} pairs the mean goes {r['mean_before']:.3g} -> "
        f"{r['mean_after']:.3g} deg."
    )


def candidate_sentence(kept: int) -> str:
    """What the pipeline's registration by local features did, for a verdict line."""
    return (
        f" The result is the registration by local features on {kept} pairs (the network does not run where "
        f"they register the pair)."
    )


def _data_limited(r: dict) -> str:
    missed = r["good"] - r["good_within_goal"]
    if "good_missed_data" not in r or not missed:
        return ""
    return (
        f"; of the {missed} that do not, {r['good_missed_data']} end where the clouds fit better than at the "
        "true pose (trimmed fit), so the data, not the refinement, place them there"
    )


def _share(x: float) -> str:
    return "-" if x != x else f"{100 * x:.1f} %"


def markdown_tables(results: dict) -> str:
    lines = []
    for setting, methods in results["settings"].items():
        info = results["setting_info"][setting]
        lines += [
            f"### {setting} ({info['pairs']} test pairs, {info['split']} split, GMCCE threshold "
            f"{info['gmcce_threshold']})",
            "",
            "| method | RMSE(R) deg | MAE(R) deg | RMSE(t) | MAE(t) | iso R deg | iso t | Chamfer | success "
            "| within 5 deg, 0.05 | the same up to symmetry | s / pair |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, r in methods.items():
            lines.append(
                f"| {name} | {r['rot_rmse']:.4f} | {r['rot_mae']:.4f} | {r['trans_rmse']:.5f} | "
                f"{r['trans_mae']:.5f} | {r['rot_iso']:.4f} | {r['trans_iso']:.5f} | {r['chamfer']:.6f} | "
                f"{100 * r['success']:.1f} % | {100 * success_share(r, RIGHT_DEG):.1f} % | "
                f"{_share(r.get('within_up_to_symmetry', float('nan')))} | {r['seconds_per_pair']:.3f} |"
            )
        if METHOD_DIT_ICP in methods and "refinement" in methods[METHOD_DIT_ICP]:
            lines += ["", refinement_line(methods[METHOD_DIT_ICP]["refinement"])]
        for name, r in methods.items():
            for key in ("verdict", "verdict_fitness"):
                if r.get(key):
                    lines += ["", verdict_line(name, r[key])]
                    if "backward_kept" in r and key == "verdict":
                        lines[-1] += (
                            f" It keeps the better fitting of its two registrations (source onto target, "
                            f"target onto source), the second on {r['backward_kept']} pairs; both are in "
                            "its time per pair."
                        )
                    elif "feature_candidate_kept" in r and key == "verdict":
                        lines[-1] += candidate_sentence(r["feature_candidate_kept"])
                    elif "extra_seconds_per_pair" in r[key]:
                        lines[-1] += (
                            f" Its second registration (target onto source) takes "
                            f"{r[key]['extra_seconds_per_pair']:.3f} s per pair more."
                        )
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
        ax.set_xticklabels(
            [f"{r:g}\u00b0\n{t:g}" for r, t in zip(ticks["rotation_thresholds"], ticks["translation_thresholds"])],
            fontsize=7,
        )
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("threshold: isotropic rotation (deg) and translation")
        ax.set_ylabel("success ratio")
        ax.set_title(setting)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_registrations(dataset: pairs_lib.PairDataset, pred, indices: np.ndarray, path: str, title: str) -> None:
    plt = plotting.pyplot()

    n = len(indices)
    fig = plt.figure(figsize=(8, 3.6 * n))
    for row, i in enumerate(indices):
        pair = dataset[int(i)]
        aligned = pair["src"] @ pred.rotation[row].T + pred.translation[row]
        rot_err = float(metrics.rotation_error_deg(jnp.asarray(pred.rotation[row]), jnp.asarray(pair["R"])))
        for col, (moving, label) in enumerate(((pair["src"], "source"), (aligned, "DIT-aligned source"))):
            ax = fig.add_subplot(n, 2, 2 * row + col + 1, projection="3d")
            ax.scatter(*pair["tgt"].T, s=1, c="tab:blue", label="target")
            ax.scatter(*moving.T, s=1, c="tab:red" if col == 0 else "tab:green", label=label)
            ax.set_title(f"pair {int(i)}: {'before' if col == 0 else f'after ({rot_err:.2f} deg error)'}", fontsize=9)
            ax.set_axis_off()
            ax.legend(fontsize=7, loc="upper left", markerscale=5)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_worst(path: str, title: str, worst: Sequence[dict]) -> None:
    """One row per method: its worst pair, before and after its estimate, from two viewpoints
    (:func:`dit_jax.pictures.plotting.draw_registration`). ``worst``: dicts with ``method``, ``pair`` (a label),
    ``src`` (N, 3), ``tgt`` (M, 3), ``R``, ``t`` (the estimate) and ``truth`` ((R, t))."""
    plt = plotting.pyplot()
    fig = plt.figure(figsize=(13, 3.4 * len(worst)))
    panels = fig.subfigures(len(worst), 1, squeeze=False)[:, 0]
    for panel, w in zip(panels, worst):
        plotting.draw_registration(panel, 0, 1, w["src"], w["tgt"], w["R"], w["t"], w["method"])
        panel.suptitle(
            f"{w['method']}, pair {w['pair']}: " + plotting.describe(w["R"], w["t"], truth=w["truth"]), fontsize=9
        )
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
        worst.append(
            {
                "method": name,
                "pair": result["worst"]["pair"],
                "src": pair["src"],
                "tgt": pair["tgt"],
                "R": np.asarray(result["worst"]["R"]),
                "t": np.asarray(result["worst"]["t"]),
                "truth": (pair["R"], pair["t"]),
            }
        )
    if missing:
        title += f"\n(not shown: {', '.join(missing)}, reused without their worst pair; rerun them to draw it)"
    if worst:
        plot_worst(path, title, worst)
    return missing


def scan_tables(results: dict) -> str:
    dit = results.get("dit")
    lines = (
        [
            f"DIT sees {dit['n_points']} points of each scan (farthest-point sampled) and iterates "
            f"{dit['n_iters']} times.",
            "",
        ]
        if dit
        else []
    )
    for pair_set, methods in results["pair_sets"].items():
        info = results["pair_set_info"][pair_set]
        criterion = info.get("criterion")
        registered = [f"registered ({criterion[0]:g} deg, {criterion[1]:g})"] if criterion else []
        lines += [
            f"### {pair_set} ({info['pairs']} pairs, about {info['angle']:.0f} degrees apart)",
            "",
            "| method | "
            + " | ".join(registered + ["median rotation error (deg)"])
            + " | "
            + " | ".join(f"within {t:g} deg" for t in SCAN_THRESHOLDS)
            + " | median translation error / extent | s / pair |",
            "|---|" + "---|" * len(registered) + "---|" + "---|" * len(SCAN_THRESHOLDS) + "---|---|",
        ]
        for name, r in methods.items():
            s = r["summary"]
            within = " | ".join(f"{s[f'within_{t:g}']} of {s['pairs']}" for t in SCAN_THRESHOLDS)
            first = f"{s['registered']} of {s['pairs']} | " if criterion else ""
            lines.append(
                f"| {name} | {first}{s['rot_median']:.2f} | {within} | {s['trans_rel_median']:.4f} | "
                f"{s['seconds_per_pair']:.2f} |"
            )
        if any("benchmark" in r["summary"] for r in methods.values()):
            lines += ["", *benchmark_table(methods, criterion)]
        if METHOD_DIT_ICP in methods:
            lines += ["", refinement_line(methods[METHOD_DIT_ICP]["summary"]["refinement"])]
        for name, r in methods.items():
            if r["summary"].get("levels"):
                lines += ["", levels_line(name, r["summary"]["levels"])]
            if r["summary"].get("verdict"):
                lines += ["", verdict_line(name, r["summary"]["verdict"])]
                if any("candidate" in row for row in r["rows"]):
                    lines[-1] += candidate_sentence(sum(row.get("candidate") == "features" for row in r["rows"]))
        lines.append("")
    return "\n".join(lines)


def benchmark_table(methods: dict, criterion) -> list[str]:
    """The 3DMatch benchmark's table of one list (rows: methods; :func:`dit_jax.evaluators.scans.benchmark_summary`)."""
    scenes = sorted({scene for r in methods.values() for scene in r["summary"].get("benchmark", {}).get("scenes", {})})
    lines = [
        "| method | registration recall (RMSE <= 0.2) | mean over scenes | "
        + " | ".join(f"recall {scene}" for scene in scenes)
        + f" | within {criterion[0]:g} deg and {criterion[1]:g} | median RRE (deg) | median RTE | median s / pair |",
        "|---|---|---|" + "---|" * len(scenes) + "---|---|---|---|",
    ]
    for name, r in methods.items():
        b = r["summary"].get("benchmark")
        if not b:
            continue
        share = lambda value: "-" if np.isnan(value) else f"{value:.1%}"
        figure = lambda value, digits: "-" if np.isnan(value) else f"{value:.{digits}f}"
        per_scene = " | ".join(share(b["scenes"][scene]["recall"]) if scene in b["scenes"] else "-" for scene in scenes)
        lines.append(
            f"| {name} | {share(b['recall'])} of {b['counted']} | {share(b['recall_scenes'])} | {per_scene} | "
            f"{share(b['criterion_share'])} of {b['pairs']} | {figure(b['rre_median'], 2)} | "
            f"{figure(b['rte_median'], 3)} | {b['seconds_median']:.2f} |"
        )
    return lines


def levels_line(name: str, levels: dict) -> str:
    """How often each verdict level was right, in one sentence."""
    parts = [f"{level} {v['pairs']} ({v['right']} right)" for level, v in levels.items() if v["pairs"]]
    return f"{name}'s verdict levels: " + ", ".join(parts) + "."


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


def write_results(out_dir: str, results: dict, table: str) -> None:
    """Writes an evaluation's ``results.json`` and its Markdown ``table`` (``results.md``) to ``out_dir``."""
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump(results, f, indent=2)
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(table)
