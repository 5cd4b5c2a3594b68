"""A run's logged metrics (``metrics.jsonl``) and its training curves, several runs in one plot."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping


def read_metrics(workdir: str) -> dict[str, list[dict]]:
    """``WORKDIR/metrics.jsonl`` split by record kind: ``{"train": [...], "val": [...]}``, each by step."""
    out: dict[str, list[dict]] = {"train": [], "val": []}
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        for line in f:
            if line.strip():
                record = json.loads(line)
                out[record.get("split", "train")].append(record)
    return {k: sorted(v, key=lambda r: r["step"]) for k, v in out.items()}


def plot_curves(runs: Mapping[str, str], path: str, title: str | None = None) -> None:
    """One figure of the training curves of several runs (``{label: workdir}``), written to ``path``.

    Panels, against the step: validation rotation error of the network alone and of full inference
    (degrees, log scale), held-out match accuracy of the network, and the training loss; for a run trained on
    a mix of settings, one more: the network alone's error on each setting (of the first such run).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (
        ("network_rotation_error", "val", "network alone: rotation error (deg)", True),
        ("rotation_error", "val", "full inference: rotation error (deg)", True),
        ("network_match_accuracy", "val", "network alone: held-out match accuracy", False),
        ("loss", "train", "training loss", True),
    )
    records_of = {label: read_metrics(workdir) for label, workdir in runs.items()}
    mixed = next((label for label, r in records_of.items() if any("/" in k for v in r["val"] for k in v)), None)
    n_panels = len(panels) + (mixed is not None)
    fig, axes = plt.subplots(1, n_panels, figsize=(4.2 * n_panels, 3.6))
    if mixed is not None:
        ax = axes[-1]
        rows = records_of[mixed]["val"]
        names = sorted({k.split("/")[0] for v in rows for k in v if k.endswith("/network_rotation_error")})
        for name in names:
            key = f"{name}/network_rotation_error"
            kept = [r for r in rows if key in r]
            ax.plot([r["step"] for r in kept], [r[key] for r in kept], marker="o", markersize=3, label=name)
        ax.set_yscale("log")
        ax.set_title(f"network alone by setting ({mixed})", fontsize=9)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6)
    for label, workdir in runs.items():
        records = read_metrics(workdir)
        for ax, (key, split, _, _) in zip(axes, panels):
            rows = [r for r in records[split] if key in r]
            ax.plot(
                [r["step"] for r in rows],
                [r[key] for r in rows],
                marker="o" if split == "val" else None,
                markersize=3,
                label=label,
            )
    for ax, (_, _, name, log) in zip(axes[: len(panels)], panels):
        if log:
            ax.set_yscale("log")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
