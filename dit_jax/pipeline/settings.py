"""The registration pipeline's settings (:class:`InferenceSettings`) and their command-line flags.

One frozen record holds every setting :mod:`dit_jax.pipeline.stages` reads, with its choices; a checkpoint stores its
own. :data:`FLAGS` gives the settings a user may change on the command line one flag name, one help text and
one set of choices each; dit-register, dit-register-series and evaluate.py add them with :func:`add_flags`
and read them back with :func:`changes`. Every such flag defaults to "as the checkpoint says". This module
imports no JAX, so the command-line tools check their input before JAX starts.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable

from dit_jax.features.descriptors import DESCRIPTORS, is_descriptor
from dit_jax.network.configs import PRECISIONS, DITConfig, Record

#: What the pipeline can do after the network: nothing, ICP or GICP (:mod:`dit_jax.geometry.icp`), or "auto"
#: (:func:`refinement_for`).
REFINEMENTS = ("none", "icp", "gicp", "auto")
#: ``refine="auto"`` refines by GICP where both clouds have at least this many points (scans, whose point
#: spacing GICP's voxel grid and local covariances need), else by ICP (sparse clouds such as ModelNet's).
DENSE_POINTS = 5_000
#: ``feature_candidate="auto"`` registers clouds of at least this many points each by local features first:
#: scans (3DMatch's fragments have 2,051 or more), not sparse shapes such as ModelNet's 1,024-point clouds,
#: where local features register far fewer pairs than the network (docs/refinement.md).
SCAN_POINTS = 2_000
#: When the pipeline registers by local features first (:attr:`InferenceSettings.feature_candidate`).
FEATURE_CANDIDATES = ("auto", "on", "off")
#: Where stage 1 centres the two clouds (:attr:`InferenceSettings.centring`).
CENTRINGS = ("auto", "shared", "separate")
#: Where local features turn the clouds' normals to face (:attr:`InferenceSettings.viewpoint`).
VIEWPOINTS = ("origin", "none")
#: How stage 4 judges a result (:attr:`InferenceSettings.verdict_rule`).
VERDICTS = ("agreement", "fitness")

#: ``centring="auto"`` centres each cloud on its own centroid where the two sampled clouds' centroids lie more
#: than this many times the larger one's radius apart, else both on their common centroid. Centred together,
#: clouds far apart shrink to two specks in the unit sphere; training offsets the target by under one radius.
FAR_APART = 10.0

#: The fields of :class:`InferenceSettings` that override the model config's inference options.
MODEL_OVERRIDES = ("n_iters", "gmcce_threshold", "gmcce_min_keep", "guard_iterations", "precision", "compute_dtype")
#: What :attr:`InferenceSettings.compute_dtype` takes (:class:`dit_jax.network.configs.DITConfig`'s own choices).
COMPUTE_DTYPES = ("float32", "bfloat16")


@dataclasses.dataclass(frozen=True)
class InferenceSettings(Record):
    """Every setting of the registration pipeline, in one place. A checkpoint stores its own (chosen on
    validation pairs by `tools/calibrate.py`); these defaults serve checkpoints that record none.

    Attributes:
      n_points: points per cloud the network sees (stage 1).
      fps_pool: clouds above this many points are thinned uniformly at random to it before farthest-point
        sampling, which keeps sampling linear in the cloud's size.
      seed: farthest-point sampling's start, ICP's subsets and the point spacing's sample: results are deterministic for a
        seed.
      centring: "shared": both clouds on the centroid of the two together, as in training; "separate": each on
        its own, for clouds far apart in the caller's frame; "auto": "separate" where the sampled clouds lie
        more than :data:`FAR_APART` radii apart, else "shared".
      n_iters, gmcce_threshold, gmcce_min_keep, guard_iterations, precision, compute_dtype: override the model config's
        (:class:`dit_jax.network.configs.DITConfig`) where set; None keeps the config's.
      refine: "icp" refines the network's estimate on the full clouds (stage 3, :func:`dit_jax.geometry.icp_refine.refine`);
        "gicp" does so with small_gicp's generalized ICP at the clouds' own point spacing
        (:func:`dit_jax.geometry.gicp.refine_gicp`: faster by far on large scans; its verdict borrows ICP's thresholds and
        bands); "auto" picks one of the two by the clouds' size (:func:`refinement_for`); "none" does not.
      feature_candidate: with a refinement, register the pair by local features first, both ways
        (:func:`dit_jax.features.matching.register_both_ways`), and the network does not run: the result is their
        better fitting direction, trusted where the two directions agree (within ``max_disagreement_features``
        degrees and ``max_offset_features`` point spacings, neither with a rival past ``max_rival_features``
        nor a turned twin past ``max_twin_features``), else "probably wrong". "on", "off", or "auto": where both clouds have
        at least :data:`SCAN_POINTS` points (scans; on sparse shapes it measured worse than the refined network
        alone, docs/refinement.md).
      viewpoint: "origin": before local features, each cloud's normals are turned to face its origin, where a
        scan in its own frame has its sensor (range scans, RGB-D fragments, LiDAR sweeps), so that one wall gets
        one description in two scans; "none": as estimated, each normal's sign arbitrary (for clouds moved out
        of their sensor's frame). Measured on rooms, the dragon, the kitchen and LiDAR (docs/refinement.md).
      descriptor: what local features match each keypoint by: "fpfh", FPFH at one radius; "histograms", FPFH at
        four radii, square-rooted and joined, for normals that face a viewpoint; "learned", the shipped network
        over the histograms, trained on rooms, or a directory of a user's own weights of it
        (:mod:`dit_jax.features.descriptors`; measured on rooms in docs/features.md).
      rotation_search: start the network from the 24 turns of :data:`dit_jax.pipeline.network_stage.SEARCH_TURNS` (clouds at
        any rotation).
      verdict_rule: "agreement": register the target onto the source too and trust the result where the two
        agree within ``max_disagreement_*`` degrees; "fitness": trust it where at least ``min_fitness`` of
        the sampled source points land on the target (one registration).
      best_direction: with ICP and the agreement verdict, return whichever direction fits the clouds better
        (:func:`dit_jax.geometry.icp.fits_better`); the verdict is the same either way.
      min_fitness: the fitness verdict's threshold, a share (above 1 trusts nothing).
      max_disagreement_network, max_disagreement_icp: the agreement verdict's thresholds (degrees) for the
        network alone and with ICP (below 0 trusts nothing, 180 everything).
      agreement_bands_network, agreement_bands_icp: how often validation results were right, band by band of
        agreement: ``((upper degrees or None, pairs, right), ...)``, increasing; quoted as
        :attr:`Result.agreement_band`.
      max_disagreement_features, max_offset_features: how close (degrees, point spacings) the features' two
        directions must lie for the result to be trusted on clouds the features register (calibrated on real scans,
        docs/verdict.md).
      max_rival_features: the features' two directions settle the pair only where neither's estimator kept a
        rival motion backed by more than this share of its own matches
        (:attr:`dit_jax.features.matching.FeatureEstimate.rival`): on rooms, the two directions share their
        matches and can agree on a wrong motion where the walls allow two (calibrated on the 3DMatch scenes,
        docs/verdict.md).
      max_twin_features: a motion the features found is trusted only where none of its quarter- or half-turned twins lays more than this share of its own count of
        points on the target (:func:`dit_jax.features.twins.twin_fit`): a box-shaped room fits itself turned,
        and no evidence from matches tells the two apart (calibrated on the 3DMatch scenes, docs/verdict.md).
      unconfirmed_min_right: a result the verdict does not trust is "unconfirmed" where at least this share of
        the validation results in its agreement band were right, else "probably wrong" (:func:`dit_jax.pipeline.verdict.level`).
    """

    n_points: int = 1000
    fps_pool: int = 20_000
    seed: int = 0
    centring: str = "auto"
    n_iters: int | None = None
    gmcce_threshold: float | None = None
    gmcce_min_keep: float | None = None
    guard_iterations: bool | None = None
    precision: str | None = None
    compute_dtype: str | None = None
    refine: str = "auto"
    feature_candidate: str = "auto"
    viewpoint: str = "origin"
    descriptor: str = "fpfh"
    rotation_search: bool = False
    verdict_rule: str = "agreement"
    best_direction: bool = True
    min_fitness: float = 0.5
    max_disagreement_network: float = 3.0
    max_disagreement_icp: float = 6.0
    agreement_bands_network: tuple | None = None
    agreement_bands_icp: tuple | None = None
    unconfirmed_min_right: float = 0.5
    max_disagreement_features: float = 1.0
    max_offset_features: float = 2.0
    max_rival_features: float = 0.5
    max_twin_features: float = 0.8

    def __post_init__(self):
        if isinstance(self.feature_candidate, bool):  # as settings stored it before "auto"
            object.__setattr__(self, "feature_candidate", "on" if self.feature_candidate else "off")
        for name, allowed in (
            ("centring", CENTRINGS),
            ("refine", REFINEMENTS),
            ("verdict_rule", VERDICTS),
            ("feature_candidate", FEATURE_CANDIDATES),
            ("viewpoint", VIEWPOINTS),
        ):
            value = getattr(self, name)
            if value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        if not is_descriptor(self.descriptor):
            raise ValueError(
                f"descriptor must be one of {', '.join(map(repr, DESCRIPTORS))} or a directory of learned "
                f"descriptor weights, got {self.descriptor!r}"
            )
        if self.precision is not None and self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(map(repr, PRECISIONS))}, got {self.precision!r}")
        if self.compute_dtype is not None and self.compute_dtype not in COMPUTE_DTYPES:
            raise ValueError(f"compute_dtype must be one of {', '.join(COMPUTE_DTYPES)}, got {self.compute_dtype!r}")
        if self.n_points < 1 or self.fps_pool < 1:
            raise ValueError(f"n_points and fps_pool must be positive, got {self.n_points} and {self.fps_pool}")
        if self.n_iters is not None and self.n_iters < 1:
            raise ValueError(f"n_iters must be at least 1, got {self.n_iters}")
        for name in ("agreement_bands_network", "agreement_bands_icp"):
            bands = getattr(self, name)
            if bands is not None:  # stored as tuples, so the settings stay immutable
                object.__setattr__(self, name, tuple(tuple(band) for band in bands))

    def model_config(self, config: DITConfig) -> DITConfig:
        """``config`` with the settings' overrides of the model's inference options applied."""
        changes = {name: getattr(self, name) for name in MODEL_OVERRIDES if getattr(self, name) is not None}
        return config.replace(**changes) if changes else config

    def refinement_for(self, src_points: int, tgt_points: int) -> str:
        """The refinement stage 3 runs on clouds of these sizes: :attr:`refine`, with "auto" resolved
        (:func:`refinement_for`)."""
        return refinement_for(self.refine, src_points, tgt_points)

    def runs_feature_candidate(self, src_points: int, tgt_points: int) -> bool:
        """Whether the pipeline registers clouds of these sizes by local features first."""
        if self.feature_candidate == "auto":
            return min(src_points, tgt_points) >= SCAN_POINTS
        return self.feature_candidate == "on"

    def max_disagreement(self, refine: str) -> float:
        """The agreement verdict's threshold (degrees) for ``refine``: the network's for "none", ICP's for a
        refinement."""
        return self.max_disagreement_network if refine == "none" else self.max_disagreement_icp

    def agreement_bands(self, refine: str) -> tuple | None:
        return self.agreement_bands_network if refine == "none" else self.agreement_bands_icp


def refinement_for(refine: str, src_points: int, tgt_points: int) -> str:
    """The refinement of ``refine`` (:data:`REFINEMENTS`) for clouds of these sizes: "auto" is "gicp" where
    both have at least :data:`DENSE_POINTS` points, else "icp"; any other value is itself."""
    if refine != "auto":
        return refine
    return "gicp" if min(src_points, tgt_points) >= DENSE_POINTS else "icp"


# ------------------------------------------------------------------------------------------ command-line flags


@dataclasses.dataclass(frozen=True)
class Flag:
    """A command-line flag that changes settings of :class:`InferenceSettings`.

    Attributes:
      name: the flag, e.g. ``"--points"``.
      fields: the :class:`InferenceSettings` fields it sets (one, or two set alike).
      help: what it does; "(default: the checkpoint's)" is added.
      type: how the text is read (``int``, ``float``, ``str``); None for a switch without a value.
      choices: the values it takes, the setting's own (``"on"`` / ``"off"`` for a yes-or-no setting).
      metavar: the value's name in ``--help``.
    """

    name: str
    fields: tuple[str, ...]
    help: str
    type: Callable | None = str
    choices: tuple[str, ...] | None = None
    metavar: str | None = None
    on_value: object = True

    @property
    def dest(self) -> str:
        return self.name.lstrip("-").replace("-", "_")

    def value(self, text):
        """The settings' value of the parsed ``text``: "on" / "off" (a switch's "on") become True / False."""
        if self.type is None:
            return self.on_value if text == "on" else None
        if self.choices == ON_OFF:
            return text == "on"
        return text


#: The values of a yes-or-no setting's flag.
ON_OFF = ("on", "off")

#: Every setting a user may change on the command line, one flag each.
FLAGS = {
    flag.dest: flag
    for flag in (
        Flag("--points", ("n_points",), "points per cloud the network sees", int, metavar="N"),
        Flag("--iters", ("n_iters",), "registration iterations of the network", int, metavar="N"),
        Flag(
            "--gmcce-threshold",
            ("gmcce_threshold",),
            "GMCCE's threshold: a correspondence is an inlier of the network's Procrustes step where its "
            "triangle-descriptor confidence exceeds TAU",
            float,
            metavar="TAU",
        ),
        Flag(
            "--bfloat16",
            ("compute_dtype",),
            "PFT's matrix products in bfloat16, parameters, softmax and norms in float32 (accuracy and speed: "
            "docs/benchmarks.md)",
            None,
            on_value="bfloat16",
        ),
        Flag(
            "--seed",
            ("seed",),
            "seed of all sampling (the clouds' points, ICP's subsets, the point spacing's sample): results are "
            "the same for a seed",
            int,
            metavar="N",
        ),
        Flag(
            "--refine",
            ("refine",),
            "how the network's estimate is refined on the full clouds: icp; gicp (small_gicp's generalized "
            "ICP at the clouds' point spacing, far faster on large scans); auto (gicp where both clouds have "
            f"{DENSE_POINTS:,} points or more, else icp); none: the network alone (faster, less accurate)",
            choices=REFINEMENTS,
        ),
        Flag(
            "--features",
            ("feature_candidate",),
            "register by local features (FPFH matches and a compatibility-graph estimator, both ways) instead "
            "of the network: the result is trusted where the two directions agree on a motion without a close "
            f"rival or turned twin, else probably wrong; auto: where both clouds have {SCAN_POINTS:,} points "
            "or more",
            choices=FEATURE_CANDIDATES,
        ),
        Flag(
            "--viewpoint",
            ("viewpoint",),
            "local features: origin turns each cloud's normals to face its origin, where a scan in its own "
            "frame has its sensor; none leaves their signs as estimated (clouds moved out of the sensor's frame)",
            choices=VIEWPOINTS,
        ),
        Flag(
            "--descriptor",
            ("descriptor",),
            "local features: what keypoints are matched by: fpfh (FPFH at one radius, as Open3D's recipes), "
            "histograms (FPFH at four radii, square-rooted and joined; needs --viewpoint origin: docs/features.md), "
            "learned (a network over the histograms, trained on rooms) or the directory of your own learned "
            "descriptor (python train.py --config configs/features.py writes WORKDIR/descriptor)",
            metavar="{fpfh,histograms,learned,DIR}",
        ),
        Flag(
            "--any-rotation",
            ("rotation_search",),
            "for clouds at any relative rotation: start the network from 24 turns of the source and go on "
            "from the best fitting (about 24 times the network's time)",
            None,
        ),
        Flag(
            "--verdict",
            ("verdict_rule",),
            "agreement: also register the target onto the source and trust the result where both agree "
            "(twice the time); fitness: trust it where enough of the source lands on the target",
            choices=VERDICTS,
        ),
        Flag(
            "--max-disagreement",
            ("max_disagreement_network", "max_disagreement_icp"),
            "agreement verdict: trust the result where the two registrations agree within DEG degrees "
            "(strict by design; larger trusts more right results and more wrong ones: docs/verdict.md)",
            float,
            metavar="DEG",
        ),
        Flag(
            "--best-direction",
            ("best_direction",),
            "with a refinement and the agreement verdict: keep whichever of the two registrations (source "
            "onto target, target onto source inverted) fits better; no extra work",
            choices=ON_OFF,
        ),
    )
}


def add_flags(parser: argparse.ArgumentParser, names: tuple[str, ...] | None = None, *, grid: bool = False) -> None:
    """Adds the flags of :data:`FLAGS` named in ``names`` (their ``dest``, e.g. ``"points"``; all by
    default) to ``parser``, each defaulting to None: "as the checkpoint says". ``grid``: each takes one value
    or more, the values a calibration tries (a list, or None)."""
    for dest in names or tuple(FLAGS):
        flag = FLAGS[dest]
        if grid:
            parser.add_argument(
                flag.name,
                type=flag.type,
                choices=flag.choices,
                nargs="+",
                default=None,
                metavar=flag.metavar,
                help=f"values to try of: {flag.help}",
            )
            continue
        if flag.type is None:  # a switch: given, the setting is on
            parser.add_argument(
                flag.name,
                action="store_const",
                const="on",
                default=None,
                help=f"{flag.help} (default: the checkpoint's)",
            )
            continue
        parser.add_argument(
            flag.name,
            type=flag.type,
            choices=flag.choices,
            default=None,
            metavar=flag.metavar,
            help=f"{flag.help} (default: the checkpoint's)",
        )


def changes(args: argparse.Namespace) -> dict:
    """The :class:`InferenceSettings` changes that the parsed flags of :data:`FLAGS` ask for (those given)."""
    found = {}
    for dest, flag in FLAGS.items():
        text = getattr(args, dest, None)
        if text is not None:
            found.update({field: flag.value(text) for field in flag.fields})
    return found
