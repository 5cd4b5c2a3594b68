"""The result of a registration (:class:`Result`): the motion, the evidence behind it and the verdict's level, with
its JSON form, its explanation in words and its plot; and the network's motion at each step before it
(:class:`Stage`)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

#: The verdict's levels (:func:`dit_jax.pipeline.verdict.level`), most confident first.
VERDICT_LEVELS = ("trusted", "unconfirmed", "probably wrong")


@dataclasses.dataclass(frozen=True)
class Stage:
    """The network's motion at one step of the pipeline, in the caller's units, with what it was judged by.

    Attributes:
      name: "network" (as the network found it) or "refined" (after the refinement) in
        :attr:`Result.stages`; :meth:`Result.as_stage` names a whole result's record as its caller asks.
      rotation: (3, 3) float64; translation: (3,) float64.
      seconds: wall time up to this step: the network's, and the refinement's for "refined".
      fitness: share of the sampled source points the motion lays on the target.
      agreement: degrees between the two directions where they were compared; NaN otherwise.
      direction: "forward" or "backward" (which direction's motion this is).
      refinement: "icp" or "gicp" for "refined", else None.
      verdict: whether this step's own evidence confirmed it.
    """

    name: str
    rotation: np.ndarray
    translation: np.ndarray
    seconds: float
    fitness: float
    agreement: float
    direction: str
    refinement: str | None
    verdict: bool


@dataclasses.dataclass(frozen=True)
class Result:
    """A registration, in the caller's units: ``tgt ~ src @ rotation.T + translation``.

    Attributes:
      rotation: (3, 3) float64.
      translation: (3,) float64.
      matrix: (4, 4) float64 homogeneous transform.
      source_indices: (n,) rows of the caller's source cloud the network saw (where ``candidate`` is
        "features", a seeded random ``n_points`` of them).
      correspondences: (n,) rows of the caller's target cloud matched to them in the last iteration (for
        "features", each one's nearest target row after the motion).
      confidence: (n,) the last iteration's Procrustes weight of each such source point, in [0, 1] (for
        "features", 1 where the nearest target row lies within 2 point spacings, else 0).
      inlier_ratio: share of the sampled source points GMCCE accepted in the last kept iteration.
      fitness: share of the sampled source points the motion lays within ``fitness_radius`` point spacings of
        the target (:func:`dit_jax.geometry.rigid.fitness`).
      seconds: wall time of the network (both directions under the agreement verdict, unless the features ran
        first; with
        ``rotation_search``, the starts' short ICPs too), excluding sampling; a first call's compilation is
        included unless the call ran several batches (:func:`dit_jax.pipeline.network_stage.network`).
      refinement: the refinement that refined the network's estimate ("icp" or "gicp"), else None.
      refine_seconds: wall time of the refinement (0 without one; both directions under the agreement verdict).
      candidate: which estimate the result is: "network" (refined where ``refinement`` says), or "features",
        registration by local features (:mod:`dit_jax.features.matching`; the network did not run).
      candidate_seconds: wall time of the registration by local features, both directions and their ICP (0
        where it did not run).
      verdict: True ("trusted") where the model's own evidence confirms the result, else False.
      level: "trusted", "unconfirmed" (not confirmed, but validation results that agreed as closely were mostly
        right) or "probably wrong" (:func:`dit_jax.pipeline.verdict.level`).
      verdict_rule: "agreement" or "fitness": which rule decided ``verdict``.
      threshold: that rule's threshold: degrees of disagreement, or a share of fitness.
      agreement: degrees between the rotation and the inverse of the one found registering the target onto
        the source (refined alike; by local features where ``candidate`` is "features" and ``first`` is
        None); NaN under the fitness verdict.
      offset: where the verdict compared the features' two directions, the distance between their
        translations in point spacings; NaN otherwise.
      max_offset: the verdict's bound on ``offset`` (point spacings); NaN where none applied.
      rival, max_rival: where local features ran, the strongest rival motion among their hypotheses, as a
        share of the winner's matches (:attr:`dit_jax.features.matching.FeatureEstimate.rival`), and the bound past which the
        features do not settle the pair alone; NaN otherwise.
      twin, max_twin: where local features ran, how many points the best quarter- or half-turned twin of the
        features' motion (the one the result lies on) lays on the target, as a share of the motion's own
        (:func:`dit_jax.features.twins.twin_fit`), and the bound past which it is not trusted; NaN otherwise.
      direction: "forward" (source onto target) or "backward" (the inverse of target onto source, kept by
        ``best_direction`` where it fits better).
      start_turn: with ``rotation_search``, the angle (degrees) of the turn of the source the kept direction's
        estimate started from; 0 for the unturned start.
      agreement_band: ``(low, high, pairs, right)``: the band of agreement (low, high] degrees this result
        falls in, how many validation results fell in it and how many of those were within 5 degrees of the
        truth; None where the settings record no bands, no agreement was measured or the band is small.
      stages: the network's motion at each step it ran, in order: "network" and, where it was refined,
        "refined" (:class:`Stage`; :meth:`stage` finds one by name). Empty where the features registered the
        pair and the network did not run.
    """

    rotation: np.ndarray
    translation: np.ndarray
    matrix: np.ndarray
    source_indices: np.ndarray
    correspondences: np.ndarray
    confidence: np.ndarray
    inlier_ratio: float
    fitness: float
    seconds: float
    refinement: str | None
    refine_seconds: float
    verdict: bool
    level: str
    verdict_rule: str
    threshold: float
    agreement: float
    direction: str
    start_turn: float
    agreement_band: tuple | None
    stages: tuple[Stage, ...] = ()
    candidate: str = "network"
    candidate_seconds: float = 0.0
    offset: float = float("nan")
    max_offset: float = float("nan")
    rival: float = float("nan")
    max_rival: float = float("nan")
    twin: float = float("nan")
    max_twin: float = float("nan")

    def stage(self, name: str) -> Stage | None:
        """The network's motion at step ``name`` ("network" or "refined"), or None where it did not run."""
        return next((stage for stage in self.stages if stage.name == name), None)

    def as_stage(self, name: str) -> Stage:
        """This result's motion and evidence as step ``name`` of a later result."""
        return Stage(
            name,
            self.rotation,
            self.translation,
            self.total_seconds,
            self.fitness,
            self.agreement,
            self.direction,
            self.refinement,
            self.verdict,
        )

    @property
    def total_seconds(self) -> float:
        """Network, refinement and any second candidate together."""
        return self.seconds + self.refine_seconds + self.candidate_seconds

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Moves (N, 3) points by the estimated transform."""
        return np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def to_json(self) -> dict:
        return {
            "matrix": self.matrix.tolist(),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "inlier_ratio": self.inlier_ratio,
            "fitness": self.fitness,
            "level": self.level,
            "verdict": self.verdict,
            "verdict_rule": self.verdict_rule,
            "threshold": self.threshold,
            "agreement_deg": _number(self.agreement),
            "offset_spacings": _number(self.offset),
            "mean_confidence": float(self.confidence.mean()) if len(self.confidence) else None,
            "points_used": int(len(self.source_indices)),
            "seconds": self.seconds,
            "refinement": self.refinement,
            "refine_seconds": self.refine_seconds,
            "direction": self.direction,
            "start_turn_deg": self.start_turn,
            "candidate": self.candidate,
            "rival_share": _number(self.rival),
            "twin_fit": _number(self.twin),
            "candidate_seconds": self.candidate_seconds,
            "agreement_band": None
            if self.agreement_band is None
            else dict(zip(("low_deg", "high_deg", "validation_pairs", "within_5_deg"), self.agreement_band)),
        }

    def to_record(self) -> dict:
        """Every field, for JSON, so that :meth:`from_record` gives this result back exactly (an array as
        ``{"dtype", "shape", "values"}``, NaN as None): a results file a run resumes from (:mod:`dit_jax.scenes.scene`)."""
        return {field.name: _to_plain(getattr(self, field.name)) for field in dataclasses.fields(self)}

    @classmethod
    def from_record(cls, record: dict) -> Result:
        """The result :meth:`to_record` wrote. Raises ValueError where ``record`` is not such a record."""
        try:
            values = _fields_from_plain(cls, record)
            values["stages"] = tuple(Stage(**_fields_from_plain(Stage, stage)) for stage in values["stages"])
            if values["agreement_band"] is not None:
                values["agreement_band"] = tuple(values["agreement_band"])
            return cls(**values)
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"not a result's record: {err}") from None

    def evidence(self) -> str:
        """One line of what the verdict rests on, e.g. for a report or a warning."""
        if self.candidate == "features":
            line = (
                f"registering by local features both ways gives motions {self.agreement:.2f} deg and "
                f"{self.offset:.1f} point spacings apart (trusted up to {self.threshold:g} deg and "
                f"{self.max_offset:g} spacings)"
            )
            if self.rival > self.max_rival:
                line += (
                    f", but another motion backs {self.rival:.2f} of the matches the features found "
                    f"(trusted up to {self.max_rival:g})"
                )
            if self.twin > self.max_twin:
                line += self._twin_clause()
            return line
        if self.verdict_rule == "agreement":
            line = (
                f"registering the target onto the source gives a rotation {self.agreement:.2f} deg from "
                f"this one's inverse (trusted up to {self.threshold:g} deg)"
            )
            if self.agreement_band is not None:
                low, high, pairs, right = self.agreement_band
                band = f"disagreed by more than {low:g}" if high is None else f"agreed within {low:g}-{high:g}"
                line += (
                    f"; of the {pairs} validation results that {band} deg, "
                    f"{100 * right / pairs:.0f} % were within 5 deg"
                )
            elif not self.verdict:
                line += "; no validation results agreed as loosely"
            return line
        return (
            f"{100 * self.fitness:.0f} % of the sampled source points land on the target "
            f"(trusted from {100 * self.threshold:.0f} %)"
        )

    def _twin_clause(self) -> str:
        return (
            f", but a quarter- or half-turned copy of the motion lays {self.twin:.2f} as many points on the "
            f"target (trusted up to {self.max_twin:g}): the scene looks alike turned"
        )

    def plot(self, path: str | os.PathLike, src, tgt, *, truth: tuple | None = None, title: str | None = None) -> str:
        """Writes a PNG of ``src`` (N, 3) and ``tgt`` (M, 3), the clouds this result registered, before and
        after the motion from two viewpoints, with the motion, inlier ratio and fitness in the title (and the
        error where ``truth`` = (R (3, 3), t (3,)) is given); where ``path`` ends in ``.html``, one page a user
        can turn (:mod:`dit_jax.pictures.view`): the target, the source as given and the source moved. Returns ``path``."""
        from dit_jax.pictures import plotting

        if os.fspath(path).lower().endswith(".html"):
            from dit_jax.pictures import view

            src, tgt = np.asarray(src, np.float64), np.asarray(tgt, np.float64)
            moved = src @ self.rotation.T + self.translation
            heading = title or f"{self.label}: {self.level}, fitness {self.fitness:.2f}"
            return view.write(path, view.page([tgt, src, moved], ["target", "source", "source moved"], title=heading))

        return plotting.plot_registration(
            path,
            np.asarray(src),
            np.asarray(tgt),
            self.rotation,
            self.translation,
            title=title,
            inlier_ratio=self.inlier_ratio,
            fitness=self.fitness,
            truth=truth,
            label=self.label,
        )

    @property
    def label(self) -> str:
        """What found the result, e.g. "DIT + GICP" or "features + ICP"."""
        found = "DIT" if self.candidate == "network" else "features"
        return f"{found} + {self.refinement.upper()}" if self.refinement else found


def _number(value: float) -> float | None:
    """A float for JSON: None for NaN."""
    return None if np.isnan(value) else float(value)


def _to_plain(value):
    """A field's value for JSON (:meth:`Result.to_record`): arrays tagged with their dtype, NaN as None."""
    if isinstance(value, np.ndarray):
        return {"dtype": value.dtype.str, "shape": list(value.shape), "values": _to_plain(value.ravel().tolist())}
    if isinstance(value, Stage):
        return {field.name: _to_plain(getattr(value, field.name)) for field in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_to_plain(item) for item in value]
    if isinstance(value, (float, np.floating)):
        return None if np.isnan(value) else float(value)
    if isinstance(value, np.generic):
        return value.item()
    return value


def _fields_from_plain(cls, record: dict) -> dict:
    """The fields of dataclass ``cls`` from ``record`` (:func:`_to_plain`'s form): NaN back in float fields."""
    values = {}
    for field in dataclasses.fields(cls):
        value = _from_plain(record[field.name])
        values[field.name] = np.nan if value is None and field.type == "float" else value
    return values


def _from_plain(value):
    """:func:`_to_plain` undone, but for NaN in a float field (:func:`_fields_from_plain`)."""
    if isinstance(value, dict) and "dtype" in value:  # an array (a stage's record is a dict of its own)
        values = [np.nan if v is None else v for v in value["values"]]
        return np.array(values, dtype=np.dtype(value["dtype"])).reshape(value["shape"])
    if isinstance(value, list):
        return [_from_plain(item) for item in value]
    return value
