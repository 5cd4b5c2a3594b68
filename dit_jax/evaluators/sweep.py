"""The rotation range: DIT's error against the rotation angle between the clouds."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

import numpy as np

from dit_jax.data import pairs as pairs_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.evaluators.common import METHOD_DIT, METHOD_DIT_ICP, progress_bar, rotation_error_deg, run_dit
from dit_jax.geometry import rigid
from dit_jax.pictures import plotting
from dit_jax.pipeline.settings import REFINEMENTS


def angle_sweep(
    checkpoint_dir: str | None,
    out_dir: str,
    *,
    data_dir: str | None = None,
    setting: str = "independent_clean",
    unseen: bool = True,
    angles: Sequence[float] = tuple(range(0, 181, 15)),
    pairs_per_angle: int = 24,
    n_points: int | None = None,
    progress: bool = True,
    refine: str = "icp",
) -> dict:
    """DIT's error against the rotation angle: test pairs of ``setting`` re-posed to rotations of exactly each
    angle about random axes (translations as drawn), through the registration pipeline as users run it: the
    network's result and, unless ``refine`` is "none", the result refined as ``register(refine=...)`` refines it
    ("icp", "gicp" or "auto"; the JSON keeps it under "icp" whichever it is).
    Writes ``angle_sweep.md``, ``.json`` and ``.png``."""
    from dit_jax.pipeline import registration

    # The network's own range: no second candidate (its results are not what the sweep measures).
    if refine not in REFINEMENTS:
        raise ValueError(f"refine must be one of {', '.join(REFINEMENTS)}, got {refine!r}")
    changes = {"refine": refine, "feature_candidate": "off"} | ({"n_points": n_points} if n_points else {})
    registrar = registration.load(checkpoint_dir, **changes)
    label = {"icp": "DIT+ICP", "gicp": "DIT+GICP", "auto": "DIT+refinement (auto)"}.get(refine)
    refine = refine != "none"
    n_points = registrar.settings.n_points
    test_shapes = shapes_lib.load_shapes(
        data_dir, "test", progress=progress, n_points=pairs_lib.shape_points(data_dir, n_points, [setting])
    )
    ds = pairs_lib.PairDataset(test_shapes, pairs_lib.PairConfig(setting=setting, unseen=unseen, n_points=n_points))
    # Pairs spread over the whole split (every category), the same ones for every angle.
    indices = np.linspace(0, len(ds) - 1, pairs_per_angle).astype(int)
    batch = ds.batch(indices)
    rng = np.random.default_rng(20261126)
    axes = rng.normal(size=(len(indices), 3))
    rows = {}
    bar = progress_bar(progress, len(angles) * len(indices), "angle sweep")
    summary = lambda e: {
        "median": float(np.median(e)),
        "within_1": float(np.mean(e <= 1)),
        "within_5": float(np.mean(e <= 5)),
        "within_10": float(np.mean(e <= 10)),
        "errors": e.tolist(),
    }
    for angle in angles:
        rotations = [rigid.axis_angle_matrix(axis, angle) for axis in axes]
        # Back to the shape's frame, then the new rotation; the translation stays as drawn.
        pairs = [
            (batch["src"][i], (batch["tgt"][i] - batch["t"][i]) @ batch["R"][i] @ rotations[i].T + batch["t"][i])
            for i in range(len(indices))
        ]
        found = run_dit(registrar, pairs, bar=bar)
        errors = {
            m: np.array([rotation_error_deg(r, truth) for r, truth in zip(est.rotation, rotations)])
            for m, est in found.items()
        }
        rows[float(angle)] = summary(errors[METHOD_DIT])
        if refine:
            rows[float(angle)]["icp"] = summary(errors[METHOD_DIT_ICP])
    if bar is not None:
        bar.close()
    results = {
        "checkpoint": checkpoint_dir and os.path.abspath(checkpoint_dir),
        "data": data_dir or "embedded",
        "setting": setting,
        "unseen": unseen,
        "pairs_per_angle": len(indices),
        "angles": rows,
    }
    results["table"] = _write_outputs(out_dir, results, label if refine else None)
    return results


def _write_outputs(out_dir: str, results: dict, label: str | None) -> str:
    """Writes the sweep's ``angle_sweep.json``, ``.md`` and ``.png`` to ``out_dir``; returns the Markdown table.
    ``label``: the refined rows' name (None: the network alone)."""
    rows, setting, unseen = results["angles"], results["setting"], results["unseen"]
    refine = label is not None
    n_pairs = results["pairs_per_angle"]
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "angle_sweep.json"), "w") as f:
        json.dump(results, f, indent=2)
    lines = [
        f"DIT on {n_pairs} {setting} pairs ({'unseen' if unseen else 'seen'} split of "
        f"{results['data']}) per angle, random axes"
        + (f"; {label} as `register` returns it (both directions refined, the better fitting kept)" if refine else ""),
        "",
        "| rotation (deg) | median error (deg) | within 5 deg | within 10 deg |"
        + (f" {label} median | {label} within 1 deg | {label} within 5 deg |" if refine else ""),
        "|---|---|---|---|" + ("---|---|---|" if refine else ""),
    ]
    for a, r in rows.items():
        line = f"| {a:g} | {r['median']:.2f} | {100 * r['within_5']:.0f} % | {100 * r['within_10']:.0f} % |"
        if refine:
            line += (
                f" {r['icp']['median']:.2f} | {100 * r['icp']['within_1']:.0f} % | {100 * r['icp']['within_5']:.0f} % |"
            )
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
        ax.plot(xs, [rows[a]["icp"]["within_1"] for a in xs], marker="s", ls="--", label=f"{label} within 1 deg")
        ax.plot(xs, [rows[a]["icp"]["within_5"] for a in xs], marker="s", ls="--", label=f"{label} within 5 deg")
    # Euler angles up to 45 degrees each: rotations up to 86 degrees, 90 % of them below 58.
    ax.axvspan(0, 58, color="tab:green", alpha=0.08, label="90 % of training rotations")
    ax.set_xlabel("rotation angle (deg)")
    ax.set_ylabel("share of pairs")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"DIT{f' and {label}' if refine else ''} against rotation angle ({setting})", fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "angle_sweep.png"), dpi=110)
    plt.close(fig)
    return table
