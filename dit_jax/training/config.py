"""A training run's recipe: :class:`TrainConfig` and the recipe files of ``configs/`` (:func:`load_config`)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import Any

from dit_jax.network import configs, losses
from dit_jax.network.configs import DITConfig


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on. Recipes are files in the repository's ``configs/``
    (``get_config()``, read by :func:`load_config`), as ``ml_collections`` ConfigDicts of these fields.

    Attributes:
      model: the network (:class:`dit_jax.network.configs.DITConfig`), e.g. ``configs.cpu(setting)``.
      setting: data setting (one of :data:`dit_jax.data.pairs.SETTINGS`).
      settings: train on a mix of these settings instead (each batch from one of them, see
        :class:`dit_jax.data.mixed.MixedPairs`; repeat one to draw it more often); validation then covers
        each of them, and the mean over them chooses the best checkpoint.
      mix_one_size: with ``settings``, every cloud of the mix is thinned at random to the fewest points any
        setting's clouds hold, so the whole mix runs one compiled train step and one validation program;
        False keeps each setting's own cloud size (a train step and a validation program per size).
      mix_points: with ``mix_one_size``, the points each cloud of the mix is thinned to (at most the fewest
        any setting holds, the default): fewer points, cheaper steps, and room for ``mix_sampling`` to vary.
        Without it, a cap: clouds of more points are thinned to it, the others keep their size.
      mix_sampling: how the mix's clouds are thinned, in training and in validation: "uniform" (points at
        random) or "varied" (each cloud by a sampler drawn at random: uniform, a density gradient or
        farthest-point sampling, see :data:`dit_jax.data.views.SAMPLERS`), so no one sampling is learned.
      data_dir: ModelNet40 directory in the h5 layout; None trains on the embedded furniture set.
      unseen: the unseen-category split (labels 0-19 train, 20-39 test).
      variant: "authors" or "peers" pairs (see :mod:`dit_jax.data.pairs`).
      max_angle: degrees; each Euler angle of a pair's turn is uniform in [-max_angle, max_angle]
        (:attr:`dit_jax.data.pairs.PairConfig.max_angle`), in training and validation alike; the turn's own
        angle is larger than any one of the three (its distribution: docs/training.md).
      n_points: points per shape.
      batch_size: pairs per step (divisible by the number of devices).
      epochs: passes over the training pairs; ``max_steps`` caps the steps if set.
      lr, weight_decay: Adam's learning rate and coupled (L2) weight decay, as PyTorch's Adam.
      lr_drops: fractions of the run after which the learning rate is multiplied by ``lr_drop_factor``.
      clip_norm: global gradient-norm clipping.
      train_iters: registration iterations unrolled in training (the authors use 2).
      differentiable: gradients through weighted Procrustes with soft correspondences (the default); False
        is the authors' detached Procrustes, where only the discrimination term trains the network. Both
        learn the quick recipe alike (docs/training.md); an earlier comparison in which the detached path
        failed was made with the temperature stuck at its clamp.
      val_fraction: share of the training shapes held out for validation (never the test split).
      val_pairs: validation pairs evaluated (the first ones, deterministic).
      eval_every, ckpt_every: steps between validations / checkpoints (also at the end).
      validate_at_start: validate the starting params before the first step (the first point of every
        curve). Off where compiling the validation costs more than the point is worth: on a short GPU lease
        it compiles the validation's registration program before any training (docs/training.md); its value
        is known from the checkpoint a run starts from.
      keep: last checkpoints kept (the best one is kept apart).
      seed: parameters, dropout, training pairs and their order.
      log_every: steps between metric lines in ``metrics.jsonl``.
      match_radius: radius of the discrimination labels (:func:`dit_jax.network.losses.match_labels`).
      train_precision: how the network's matrix products are computed in the train step only (see
        :attr:`dit_jax.network.configs.DITConfig.precision`): None (the default) as the model says; "bfloat16" takes
        bfloat16 operands with float32 accumulation, while the parameters, the optimiser, the geometry and the
        losses stay float32. Validation and the saved model keep the model's own precision. "auto" times the
        step at both when the run starts and takes bfloat16 only where it is clearly faster on this machine
        (:mod:`dit_jax.training.precision`); the run's ``train_config.json`` records the choice. On a CPU
        bfloat16 makes the cpu recipe's step no faster: its cost is the softmax and narrow attention heads,
        which bfloat16 operands do not shorten (docs/benchmarks.md).
      correspondence_weight: weight of the correspondence term (:func:`dit_jax.network.losses.correspondence_loss`,
        not the authors'); 0 trains the authors' objective.
      init_from: a model checkpoint (:mod:`dit_jax.network.checkpoint`, e.g. ``WORKDIR/model`` of an earlier run)
        whose params start this run, with a fresh optimiser: fine-tuning, e.g. a clean model on a noisy
        setting. Its network shape must match ``model``'s, or have fewer PFT layers
        (``--config.model.n_blocks=4`` from a 2-block checkpoint): then the network is grown in depth by
        :func:`dit_jax.network.pft.deepen` and starts out computing what the checkpoint computes.
    """

    model: DITConfig = dataclasses.field(default_factory=configs.cpu)
    setting: str = "clean"
    settings: tuple[str, ...] = ()
    mix_one_size: bool = True
    mix_points: int | None = None
    mix_sampling: str = "uniform"
    data_dir: str | None = None
    unseen: bool = False
    variant: str = "authors"
    max_angle: float = 45.0
    n_points: int = 1000
    batch_size: int = 8
    epochs: int = 100
    max_steps: int | None = None
    lr: float = 1e-3
    weight_decay: float = 1e-4
    lr_drops: tuple[float, ...] = (0.3, 0.6, 0.8)
    lr_drop_factor: float = 0.1
    clip_norm: float = 10.0
    train_iters: int = 2
    differentiable: bool = True
    val_fraction: float = 0.1
    val_pairs: int = 64
    eval_every: int = 200
    ckpt_every: int = 100
    validate_at_start: bool = True
    keep: int = 3
    seed: int = 0
    log_every: int = 10
    match_radius: float = losses.MATCH_RADIUS
    correspondence_weight: float = 0.0
    init_from: str | None = None
    train_precision: str | None = None

    def __post_init__(self):
        if self.train_precision not in (None, "auto", *configs.PRECISIONS):
            raise ValueError(
                f"train_precision must be one of {', '.join(configs.PRECISIONS)}, auto (or unset), "
                f"got {self.train_precision!r}"
            )

    def model_config(self) -> DITConfig:
        return self.model

    def train_model_config(self) -> DITConfig:
        """The network as the train step computes it: :meth:`model_config` at ``train_precision``."""
        if self.train_precision == "auto":
            raise ValueError(
                'train_precision "auto" is chosen when a run starts (dit_jax.training.precision.choose); '
                "resolve it before building a train step"
            )
        if self.train_precision is None:
            return self.model
        return self.model.replace(precision=self.train_precision)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["model"] = self.model.to_dict()
        d["lr_drops"] = list(self.lr_drops)
        d["settings"] = list(self.settings)
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> TrainConfig:
        """The config :meth:`to_json` (or a checkpoint's ``train_config``) wrote. Records that name the model
        by preset (``"model": "cpu"`` with ``model_overrides``) are read as that preset with the changes."""
        d = dict(d)
        overrides = dict(tuple(kv) for kv in d.pop("model_overrides", ()))
        model = d.get("model", "cpu")
        d["model"] = (
            configs.get(model, d.get("setting", "clean")).replace(**overrides)
            if isinstance(model, str)
            else DITConfig.from_dict(model)
        )
        d["lr_drops"] = tuple(d.get("lr_drops", ()))
        d["settings"] = tuple(d.get("settings", ()))
        d.setdefault("mix_one_size", False)  # records from before the field: each setting its own size
        return cls(**d)

    def to_config_dict(self):
        """This config as an ``ml_collections.ConfigDict`` (what a file in ``configs/`` returns); unset
        optional fields are typed placeholders, so the command line can set them."""
        import typing

        from ml_collections import ConfigDict
        from ml_collections.config_dict import placeholder

        def as_dict(record) -> dict:
            hints = typing.get_type_hints(type(record))
            out = {}
            for field in dataclasses.fields(record):
                value = getattr(record, field.name)
                if dataclasses.is_dataclass(value):
                    value = ConfigDict(as_dict(value))
                elif value is None:
                    value = placeholder(next(t for t in typing.get_args(hints[field.name]) if t is not type(None)))
                out[field.name] = value
            return out

        return ConfigDict(as_dict(self))

    @classmethod
    def from_config_dict(cls, config) -> TrainConfig:
        """The TrainConfig of an ``ml_collections.ConfigDict`` made by :meth:`to_config_dict` (and changed)."""
        d = config.to_dict()
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown TrainConfig fields: {', '.join(unknown)}")
        return cls.from_json(d)


def recipe_from_config_dict(config):
    """The recipe a ``configs/`` file's ConfigDict gives: a :class:`TrainConfig` for DIT, or the learned
    descriptor's :class:`dit_jax.training.descriptor.DescriptorTrainConfig` where it has a ``descriptor`` field."""
    if "descriptor" in config:
        from dit_jax.training.descriptor import DescriptorTrainConfig

        return DescriptorTrainConfig.from_config_dict(config)
    return TrainConfig.from_config_dict(config)


def recipe_from_json(record: Mapping[str, Any]):
    """The recipe a run's ``train_config.json`` holds, of either kind (:func:`recipe_from_config_dict`)."""
    if record.get("kind") == "descriptor":
        from dit_jax.training.descriptor import DescriptorTrainConfig

        return DescriptorTrainConfig.from_json(record)
    return TrainConfig.from_json(record)


def load_config(path: str | os.PathLike):
    """The recipe of a recipe file (``configs/quick.py``): its ``get_config()``, as :func:`recipe_from_config_dict`
    reads it."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"recipe_{os.path.basename(path)[:-3]}", os.fspath(path))
    if spec is None or not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such recipe file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return recipe_from_config_dict(module.get_config())
