"""What every kind of evaluation shares: the method names, DIT's estimates from the registration pipeline as a
typed record, and the verdict's and the refinement's summaries."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from dit_jax.geometry import rigid

if TYPE_CHECKING:
    from dit_jax.pipeline.result import Result, Stage

#: The network alone.
METHOD_DIT = "DIT"
#: The network refined by the settings' refinement (ICP on sparse clouds, GICP on scans: ``refine="auto"``).
METHOD_DIT_ICP = "DIT+ICP"
#: The default pipeline: on scans, registration by local features (:func:`dit_jax.pipeline.stages.features_first`);
#: elsewhere DIT+ICP.
METHOD_PIPELINE = "pipeline"
#: The rows that come from the registration pipeline (the rest are baselines).
PIPELINE_METHODS = (METHOD_DIT, METHOD_DIT_ICP, METHOD_PIPELINE)
#: What "right" means where the data give no criterion of their own: within this many degrees of rotation (on
#: ModelNet40's pairs, with 0.05 of translation: :func:`success_share`).
RIGHT_DEG = 5.0
#: Rotation thresholds (degrees) of the real-scan tables and curves.
SCAN_THRESHOLDS = (1.0, 2.0, 5.0, 10.0)


@dataclasses.dataclass(frozen=True)
class Estimates:
    """One method's estimates of P pairs.

    Attributes:
      rotation: (P, 3, 3); translation: (P, 3): ``tgt ~ src @ R.T + t`` per pair.
      seconds: (P,) wall time per pair.
      fitness: (P,) the verdict's fitness (DIT only, else None).
      agreement: (P,) degrees between the two directions (DIT under the agreement verdict, else None).
      backward: (P,) bool, the inverse of the target-onto-source motion was kept (DIT+ICP only, else None).
      verdict: (P,) bool, the pipeline's own verdict (the pipeline row only, else None: the other rows'
        verdicts are scored from their agreement or fitness).
      candidate: (P,) str, which estimate the pipeline kept, "network" or "features" (the pipeline row only).
      level: (P,) str, the verdict's level, "trusted", "unconfirmed" or "probably wrong" (the pipeline row
        only).
    """

    rotation: np.ndarray
    translation: np.ndarray
    seconds: np.ndarray
    fitness: np.ndarray | None = None
    agreement: np.ndarray | None = None
    backward: np.ndarray | None = None
    verdict: np.ndarray | None = None
    candidate: np.ndarray | None = None
    level: np.ndarray | None = None

    @classmethod
    def from_stages(cls, stages: Sequence[Stage]) -> Estimates:
        """From one step of the network's motion per pair (:class:`dit_jax.pipeline.result.Stage`), each timed up to
        that step."""
        agreement = np.array([s.agreement for s in stages])
        refined = bool(stages) and stages[0].refinement is not None
        return cls(
            rotation=np.stack([s.rotation for s in stages]),
            translation=np.stack([s.translation for s in stages]),
            seconds=np.array([s.seconds for s in stages]),
            fitness=np.array([s.fitness for s in stages]),
            agreement=None if np.isnan(agreement).all() else agreement,
            backward=np.array([s.direction == "backward" for s in stages]) if refined else None,
        )

    @classmethod
    def from_results(cls, results: Sequence[Result]) -> Estimates:
        """From the pipeline's :class:`dit_jax.pipeline.result.Result` s, each timed whole, with their own verdicts."""
        return dataclasses.replace(
            cls.from_stages([r.as_stage("result") for r in results]),
            verdict=np.array([r.verdict for r in results]),
            candidate=np.array([r.candidate for r in results]),
            level=np.array([r.level for r in results]),
        )


def run_dit(registrar, pairs: Sequence[tuple], *, batch_size: int = 8, bar=None) -> dict[str, Estimates]:
    """DIT's estimates of ``pairs`` ((src, tgt), ...) through the registration pipeline, as users get them:
    ``{METHOD_DIT: the network's result, METHOD_DIT_ICP: the refined one, METHOD_PIPELINE: the pipeline's
    result}`` (the second where the registrar's settings refine, the third where they also register by local
    features). Each result keeps the network's stages before it, so one run gives all three, unless the
    features settle some pairs before the network runs (dense scans): then the network's rows come from a
    second run of the pipeline with the features off."""
    settings = registrar.settings
    results = registrar.register_pairs(pairs, batch_size=batch_size, on_pair=bar.update if bar else None)
    network_results = results
    if any(not r.stages for r in results):
        network_results = registrar.register_pairs(pairs, batch_size=batch_size, feature_candidate="off")
    out = {METHOD_DIT: Estimates.from_stages([r.stage("network") for r in network_results])}
    if settings.refine != "none":
        # Where the network ran after the features and landed out of their reach, it was not refined.
        refined = [r.stage("refined") or r.stage("network") for r in network_results]
        out[METHOD_DIT_ICP] = Estimates.from_stages(refined)
        if settings.feature_candidate != "off":
            out[METHOD_PIPELINE] = Estimates.from_results(results)
    return out


def success_share(stats: dict, degrees: float = RIGHT_DEG) -> float:
    """The share of pairs within ``degrees`` of rotation (and the sweep's paired translation threshold: 0.05 at
    5 degrees), read off the success curve an evaluation stores for a method (``stats["success_curve"]``)."""
    curve = stats["success_curve"]
    return curve["ratio"][curve["rotation_thresholds"].index(degrees)]


def progress_bar(enabled: bool, total: int, desc: str):
    """A tqdm bar over ``total`` pairs, or None where ``enabled`` is false."""
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="pair", dynamic_ncols=True)


def verdict_summary(errors: np.ndarray, verdicts: np.ndarray, rule: str, right_deg: float = RIGHT_DEG) -> dict:
    """How well a verdict separates results: errors (P,) in degrees, verdicts (P,) True = trusted; ``rule``
    says in words what it trusts (e.g. "agreement within 5.0 deg").

    ``failures_caught``: of the results more than ``right_deg`` off, the share flagged; ``passed_right``: of
    the results trusted, the share within ``right_deg`` (NaN where there are none)."""
    wrong = errors > right_deg
    caught = float(np.mean(~verdicts[wrong])) if wrong.any() else float("nan")
    right = float(np.mean(~wrong[verdicts])) if verdicts.any() else float("nan")
    return {
        "rule": rule,
        "failures": int(wrong.sum()),
        "failures_caught": caught,
        "passed": int(verdicts.sum()),
        "passed_right": right,
        "right_deg": right_deg,
    }


def agreement_bands(errors: np.ndarray, agreement: np.ndarray, edges, right_deg: float = RIGHT_DEG) -> list[list]:
    """How often results were right, band by band of the agreement verdict's evidence: errors (P,) and
    agreement (P,) in degrees; ``edges`` the bands' upper ends, increasing. Returns one ``[upper, pairs,
    right]`` per band (previous edge, edge], then ``[None, pairs, right]`` for those beyond the last edge:
    how many results fell in it and how many of them were within ``right_deg``. What
    :class:`dit_jax.pipeline.result.Result` quotes beside a verdict (``verdict_agreement_bands``)."""
    errors, agreement = np.asarray(errors, np.float64), np.asarray(agreement, np.float64)
    bands, low = [], -np.inf
    for high in [*edges, np.inf]:
        inside = (agreement > low) & (agreement <= high)
        bands.append(
            [None if np.isinf(high) else float(high), int(inside.sum()), int((inside & (errors <= right_deg)).sum())]
        )
        low = high
    return bands


def agreement_rule(max_disagreement: float) -> str:
    """The agreement verdict's rule in words (see :class:`dit_jax.pipeline.registration.Registrar`)."""
    return f"target onto source agrees within {max_disagreement:g} deg"


def fitness_rule(min_fitness: float) -> str:
    """The fitness verdict's rule in words."""
    return f"fitness >= {min_fitness:.2f}"


def refinement_summary(
    before: np.ndarray,
    after: np.ndarray,
    beats_truth: np.ndarray | None = None,
    good_deg: float = 10.0,
    goal_deg: float = 1.0,
) -> dict:
    """What ICP did to DIT's estimates: rotation errors (P,) in degrees before and after. Of the pairs DIT
    alone had within ``good_deg``, how many end within ``goal_deg`` (and the worst of them); the mean change
    over those pairs and over all. With ``beats_truth`` (P,) bool (the refined motion fits the clouds better
    than the truth), ``good_missed_data``: how many of the misses the data themselves place elsewhere, which
    no refinement that fits the points can bring within the goal."""
    good = before <= good_deg
    extra = {}
    if beats_truth is not None:
        extra["good_missed_data"] = int(np.sum(good & (after > goal_deg) & np.asarray(beats_truth, bool)))
    return extra | {
        "good_deg": good_deg,
        "goal_deg": goal_deg,
        "good": int(good.sum()),
        "good_within_goal": int(np.sum(after[good] <= goal_deg)),
        "good_worst_after": float(after[good].max()) if good.any() else float("nan"),
        "good_mean_before": float(before[good].mean()) if good.any() else float("nan"),
        "good_mean_after": float(after[good].mean()) if good.any() else float("nan"),
        "mean_before": float(before.mean()),
        "mean_after": float(after.mean()),
        "pairs": int(len(before)),
    }


def rotation_error_deg(rotation: np.ndarray, truth: np.ndarray) -> float:
    return rigid.rotation_angle_deg(np.asarray(rotation, np.float64).T @ truth)


def rescore_agreement(results: dict, max_disagreement: dict) -> dict:
    """Re-scores the agreement verdict of an :func:`evaluate` or :func:`evaluate_scans` output (its
    ``results.json``) at new thresholds ({"none": degrees, "icp": degrees}), from the agreement each pair
    kept: nothing is registered again, and every other figure stays as measured. DIT's and DIT+ICP's verdict
    summaries (and, for scans, each row's ``verdict``) are replaced in place; returns ``results``.

    Raises ValueError where an agreement verdict was reported without its per-pair evidence (older outputs),
    which only a new evaluation can score."""

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
            r["verdict"] = (
                verdict_summary(
                    errors, agreement <= threshold(method), agreement_rule(threshold(method)), r["verdict"]["right_deg"]
                )
                | extra
            )
    for pair_set, methods in results.get("pair_sets", {}).items():
        for method in (METHOD_DIT, METHOD_DIT_ICP):
            r = methods.get(method)
            verdict = r and r["summary"].get("verdict")
            if not verdict or not verdict["rule"].startswith("target onto source"):
                continue  # no verdict, or the fitness verdict, whose threshold this does not move
            for row in r["rows"]:
                row["verdict"] = bool(row["agreement"] <= threshold(method))
            r["summary"]["verdict"] = verdict_summary(
                np.array([row["rot_err"] for row in r["rows"]]),
                np.array([row["verdict"] for row in r["rows"]]),
                agreement_rule(threshold(method)),
                verdict["right_deg"],
            )
    return results
