"""Training DIT: optax, orbax checkpoints, data parallelism over a device mesh, resumable.

:func:`train` is the whole job behind ``python train.py``. Its pieces are usable on their own:
:func:`make_optimizer`, :func:`init_state`, :func:`make_train_step` (a jitted, sharded step that skips
non-finite updates) and :func:`validate`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dit_jax import configs, losses, metrics, model, pft
from dit_jax.configs import DITConfig
from dit_jax.data import pairs as pairs_lib
from dit_jax.data import prefetch
from dit_jax.data import shapes as shapes_lib


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on. Recipes are files in the repository's ``configs/``
    (``get_config()``, read by :func:`load_config`), as ``ml_collections`` ConfigDicts of these fields.

    Attributes:
      model: the network (:class:`dit_jax.configs.DITConfig`), e.g. ``configs.cpu(setting)``.
      setting: data setting (one of :data:`dit_jax.data.pairs.SETTINGS`).
      settings: train on a mix of these settings instead (each batch from one of them, see
        :class:`dit_jax.data.pairs.MixedPairs`; repeat one to draw it more often); validation then covers
        each of them, and the mean over them chooses the best checkpoint.
      mix_one_size: with ``settings``, every cloud of the mix is thinned at random to the fewest points any
        setting's clouds hold, so the whole mix runs one compiled train step and one validation program;
        False keeps each setting's own cloud size (a train step and a validation program per size).
      mix_points: with ``mix_one_size``, the points each cloud of the mix is thinned to (at most the fewest
        any setting holds, the default): fewer points, cheaper steps, and room for ``mix_sampling`` to vary.
        Without it, a cap: clouds of more points are thinned to it, the others keep their size.
      mix_sampling: how the mix's clouds are thinned, in training and in validation: "uniform" (points at
        random) or "varied" (each cloud by a sampler drawn at random: uniform, a density gradient or
        farthest-point sampling, see :data:`dit_jax.data.pairs.SAMPLERS`), so no one sampling is learned.
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
      match_radius: radius of the discrimination labels (:func:`dit_jax.losses.match_labels`).
      train_precision: how the network's matrix products are computed in the train step only (see
        :attr:`dit_jax.configs.DITConfig.precision`): None (the default) as the model says; "bfloat16" takes
        bfloat16 operands with float32 accumulation, while the parameters, the optimiser, the geometry and the
        losses stay float32. Validation and the saved model keep the model's own precision. On a CPU it makes
        the cpu recipe's step no faster, since XLA's CPU backend runs the batched attention products and the
        softmax in float32 either way (docs/benchmarks.md).
      correspondence_weight: weight of the correspondence term (:func:`dit_jax.losses.correspondence_loss`,
        not the authors'); 0 trains the authors' objective.
      init_from: a model checkpoint (:mod:`dit_jax.checkpoint`, e.g. ``WORKDIR/model`` of an earlier run)
        whose params start this run, with a fresh optimiser: fine-tuning, e.g. a clean model on a noisy
        setting. Its network shape must match ``model``'s, or have fewer PFT layers
        (``--config.model.n_blocks=4`` from a 2-block checkpoint): then the network is grown in depth by
        :func:`dit_jax.pft.deepen` and starts out computing what the checkpoint computes.
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
        if self.train_precision is not None and self.train_precision not in configs.PRECISIONS:
            raise ValueError(
                f"train_precision must be one of {', '.join(configs.PRECISIONS)} (or unset), "
                f"got {self.train_precision!r}"
            )

    def model_config(self) -> DITConfig:
        return self.model

    def train_model_config(self) -> DITConfig:
        """The network as the train step computes it: :meth:`model_config` at ``train_precision``."""
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


def load_config(path: str | os.PathLike) -> TrainConfig:
    """The :class:`TrainConfig` of a recipe file (``configs/quick.py``): its ``get_config()``."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"recipe_{os.path.basename(path)[:-3]}", os.fspath(path))
    if spec is None or not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such recipe file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return TrainConfig.from_config_dict(module.get_config())


class TrainState(struct.PyTreeNode):
    """All that a step changes. ``opt_state`` is the optimiser's state over the parameters as one vector
    (:func:`_flat`). ``rng`` is a raw uint32 key so orbax stores it as a plain array."""

    step: jax.Array
    params: Any
    opt_state: Any
    rng: jax.Array
    skipped: jax.Array  # steps whose loss or gradients were not finite, and so were not applied


# ------------------------------------------------------------------------------------------ optimisation


def lr_schedule(config: TrainConfig, total_steps: int) -> optax.Schedule:
    """Constant ``lr``, times ``lr_drop_factor`` after each fraction in ``lr_drops`` of the run."""
    boundaries = {max(1, int(f * total_steps)): config.lr_drop_factor for f in config.lr_drops}
    return optax.piecewise_constant_schedule(config.lr, boundaries)


def make_optimizer(config: TrainConfig, total_steps: int) -> optax.GradientTransformation:
    """Clipping, then PyTorch-style Adam with L2 weight decay added to the gradient, then the schedule."""
    return optax.chain(
        optax.clip_by_global_norm(config.clip_norm),
        optax.add_decayed_weights(config.weight_decay),
        optax.scale_by_adam(),
        optax.scale_by_learning_rate(lr_schedule(config, total_steps)),
    )


def init_state(config: TrainConfig, optimizer: optax.GradientTransformation) -> TrainState:
    """A run's first state: fresh parameters from ``config.seed``, ``optimizer``'s state, step 0."""
    key = jax.random.PRNGKey(config.seed)
    params = model.init(jax.random.fold_in(key, 1), config.model_config())
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        opt_state=optimizer.init(_flat(params)),
        rng=key,
        skipped=jnp.zeros((), jnp.int32),
    )


def _flat(tree) -> jax.Array:
    """Every leaf of ``tree``, raveled and concatenated in tree order: (P,), P the number of parameters.

    The optimiser, the finiteness check and the skip of a train step work on this one vector: per leaf, each of
    a hundred small arrays got loops of its own, and they made much of the step's compilation.
    """
    return jax.flatten_util.ravel_pytree(tree)[0]


def _pair_loss(params, pair, model_config: DITConfig, config: TrainConfig):
    """One pair's loss and its terms and errors; ``pair`` is ``(src, tgt, R, t, dropout_key)``."""
    src, tgt, rotation_gt, translation_gt, pair_key = pair
    its = model.unroll(
        params, src, tgt, model_config, config.train_iters, differentiable=config.differentiable, dropout_key=pair_key
    )
    total, terms = losses.dit_loss(
        its,
        src,
        tgt,
        rotation_gt,
        translation_gt,
        match_radius=config.match_radius,
        correspondence_weight=config.correspondence_weight,
    )
    terms["rotation_error"] = metrics.rotation_error_deg(its.rotation[-1], rotation_gt)
    terms["translation_error"] = metrics.translation_error(its.translation[-1], translation_gt)
    return total, terms


def batch_loss_and_grads(params, batch, model_config: DITConfig, config: TrainConfig, key, devices: int = 1):
    """``((loss, terms), grads)``: the batch's mean loss, the mean of each term and error, and the gradient
    of the mean loss with respect to ``params``. ``batch``: ``src`` (B, N, 3), ``tgt`` (B, M, 3), ``R`` (B, 3, 3),
    ``t`` (B, 3).

    The batch (B pairs) splits into ``devices`` equal parts, one per device of the mesh (vmapped, so the
    sharded axis stays sharded); pair ``i`` draws its dropout from ``split(key, B)[i]``. On a CPU each part's
    pairs run one after another, each pair's forward and backward pass together (a scan that adds up the
    gradients): one pair's arrays stay in cache, and no pair's activations wait for the others' backward
    pass. On accelerators the pairs are vmapped and the batch's mean loss differentiated at once.
    """
    n_pairs = batch["src"].shape[0]
    pairs = (batch["src"], batch["tgt"], batch["R"], batch["t"], jax.random.split(key, n_pairs))

    def by_device(part):  # the parts' results, one part per device
        if devices == 1:  # the same sums, without a batching pass over the whole traced loss
            return part(pairs)
        return jax.vmap(part)(jax.tree.map(lambda a: a.reshape(devices, n_pairs // devices, *a.shape[1:]), pairs))

    if jax.default_backend() != "cpu":

        def mean_loss(p):
            totals, terms = by_device(
                lambda part_pairs: jax.vmap(lambda *pair: _pair_loss(p, pair, model_config, config))(*part_pairs)
            )
            return jnp.mean(totals), jax.tree.map(jnp.mean, terms)

        return jax.value_and_grad(mean_loss, has_aux=True)(params)

    pair_value_and_grad = jax.value_and_grad(_pair_loss, has_aux=True)

    def part(part_pairs):
        def add_pair(grad_sum, pair):
            (total, terms), grads = pair_value_and_grad(params, pair, model_config, config)
            return jax.tree.map(jnp.add, grad_sum, grads), (total, terms)

        return jax.lax.scan(add_pair, jax.tree.map(jnp.zeros_like, params), part_pairs)

    grad_sums, (totals, terms) = by_device(part)
    if devices > 1:
        grad_sums = jax.tree.map(lambda g: jnp.sum(g, axis=0), grad_sums)
    grads = jax.tree.map(lambda g: g / n_pairs, grad_sums)
    return (jnp.mean(totals), jax.tree.map(jnp.mean, terms)), grads


def make_train_step(config: TrainConfig, optimizer: optax.GradientTransformation, mesh: Mesh) -> Callable:
    """A jitted ``step(state, batch) -> (state, metrics)``: params replicated, the batch split over ``mesh``.

    A step whose loss or gradients are not all finite changes nothing but ``step`` and ``skipped``.
    """
    model_config = config.train_model_config()
    replicated = NamedSharding(mesh, PartitionSpec())

    def step(state: TrainState, batch):
        key = jax.random.fold_in(state.rng, state.step)
        (loss, terms), grads = batch_loss_and_grads(state.params, batch, model_config, config, key, mesh.devices.size)
        flat_params, unflatten = jax.flatten_util.ravel_pytree(state.params)
        flat_grads = _flat(grads)
        updates, opt_state = optimizer.update(flat_grads, state.opt_state, flat_params)
        finite = jnp.isfinite(loss) & jnp.all(jnp.isfinite(flat_grads))
        new_state = state.replace(
            step=state.step + 1,
            params=unflatten(jnp.where(finite, optax.apply_updates(flat_params, updates), flat_params)),
            opt_state=jax.tree.map(lambda new, old: jnp.where(finite, new, old), opt_state, state.opt_state),
            skipped=state.skipped + (~finite).astype(jnp.int32),
        )
        out = dict(terms, loss=loss, grad_norm=optax.global_norm(flat_grads), finite=finite)
        return new_state, out

    return jax.jit(step, out_shardings=(replicated, replicated), donate_argnums=0)


def initialize_distributed(
    coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None
) -> None:
    """Joins a multi-process run (``jax.distributed.initialize``); call before anything touches a device.

    Each argument left None comes from the environment (``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``,
    ``JAX_PROCESS_ID``), else from a cluster JAX detects itself (SLURM, Open MPI, Kubernetes, TPU pods).
    Processes on CPUs exchange gradients through gloo, JAX's CPU collectives.
    """
    env = os.environ
    coordinator = coordinator or env.get("JAX_COORDINATOR_ADDRESS")
    if num_processes is None and env.get("JAX_NUM_PROCESSES"):
        num_processes = int(env["JAX_NUM_PROCESSES"])
    if process_id is None and env.get("JAX_PROCESS_ID"):
        process_id = int(env["JAX_PROCESS_ID"])
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator, num_processes, process_id)


def is_primary() -> bool:
    """Whether this process writes the run's log and config: process 0 (orbax coordinates checkpoints)."""
    return jax.process_index() == 0


def make_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``data`` over all devices (of all hosts)."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), ("data",))


def shard_batch(batch: Mapping[str, np.ndarray], mesh: Mesh) -> dict[str, jax.Array]:
    """Places this process's part of a global batch on the mesh, split along the batch axis.

    Every process builds the whole global batch (pairs are cheap and deterministic) and contributes the rows
    of its own devices, so one and several hosts run the same code.
    """
    sharding = NamedSharding(mesh, PartitionSpec("data"))
    n_proc, proc = jax.process_count(), jax.process_index()
    out = {}
    for key in ("src", "tgt", "R", "t"):
        value = np.asarray(batch[key])
        local = np.array_split(value, n_proc)[proc] if n_proc > 1 else value
        out[key] = jax.make_array_from_process_local_data(sharding, local, value.shape)
    return out


def replicate(tree, mesh: Mesh):
    """``tree`` on every device of ``mesh`` (parameters and optimizer state are replicated)."""
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


# ------------------------------------------------------------------------------------------ data


def split_validation(shapes: shapes_lib.Shapes, fraction: float) -> tuple[shapes_lib.Shapes, shapes_lib.Shapes]:
    """Training and validation shapes: a fixed share of the training split, the same for every seed."""
    order = np.random.default_rng(20261122).permutation(len(shapes.labels))
    n_val = max(1, int(round(fraction * len(order)))) if fraction > 0 else 0
    val, train = np.sort(order[:n_val]), np.sort(order[n_val:])
    take = lambda rows: shapes_lib.Shapes(
        shapes.points[rows], shapes.labels[rows], shapes.ids[rows], shapes.shape_names
    )
    return take(train), take(val)


def validation_batches(
    data_dir: str | None,
    settings,
    *,
    count: int = 24,
    n_points: int = 1000,
    unseen: bool = True,
    prepared_dir: str | None = None,
) -> dict[str, dict]:
    """Fixed validation pairs for choosing settings outside training (inference options, baselines' knobs):
    ``count`` pairs per setting from the training split's held-out shapes (:func:`split_validation`; only
    categories 0-19 with ``unseen``), spread over all of them. Returns ``{setting: batch}`` (see
    :meth:`dit_jax.data.pairs.PairDataset.batch`); never a test pair."""
    shapes = shapes_lib.load_shapes(
        data_dir, "train", data_dir=prepared_dir, n_points=pairs_lib.shape_points(data_dir, n_points, settings)
    )
    _, val_shapes = split_validation(shapes, TrainConfig().val_fraction)
    batches = {}
    for setting in settings:
        ds = pairs_lib.PairDataset(val_shapes, pairs_lib.PairConfig(setting=setting, n_points=n_points))
        if unseen:
            ds.rows = ds.rows[val_shapes.labels[ds.rows] < 20]
        batches[setting] = ds.batch(np.linspace(0, len(ds) - 1, count).astype(int))
    return batches


def make_datasets(config: TrainConfig, prepared_dir: str | None = None, progress: bool = True):
    """(training pairs, validation pairs) from the training split of the chosen source: two
    :class:`~dit_jax.data.pairs.PairDataset`, or two :class:`~dit_jax.data.pairs.MixedPairs` with
    ``config.settings``. ``progress``: TFDS's progress bars if the shapes are prepared now."""
    settings = config.settings or (config.setting,)
    n_shape = pairs_lib.shape_points(config.data_dir, config.n_points, settings)
    shapes = shapes_lib.load_shapes(
        config.data_dir, "train", n_points=n_shape, data_dir=prepared_dir, progress=progress
    )
    train_shapes, val_shapes = split_validation(shapes, config.val_fraction)
    common = dict(setting=config.setting, variant=config.variant, n_points=config.n_points, max_angle=config.max_angle)
    train_config = pairs_lib.PairConfig(train=True, seed=config.seed, unseen=config.unseen, **common)
    # Validation pairs are fixed (seeded by index) test-style pairs of held-out training shapes; with the
    # unseen split they keep the training categories (a test-style unseen config would keep 20-39 instead).
    val_config = pairs_lib.PairConfig(train=False, unseen=False, **common)
    if config.settings:
        thinning = dict(one_size=config.mix_one_size, points=config.mix_points, sampling=config.mix_sampling)
        train = pairs_lib.MixedPairs(train_shapes, train_config, config.settings, **thinning)
        val = pairs_lib.MixedPairs(val_shapes, val_config, tuple(dict.fromkeys(config.settings)), **thinning)
    else:
        train = pairs_lib.PairDataset(train_shapes, train_config)
        val = pairs_lib.PairDataset(val_shapes, val_config)
    if config.unseen:
        keep = (val_shapes.labels >= 0) & (val_shapes.labels < 20)
        for ds in getattr(val, "datasets", {"": val}).values():
            ds.rows = ds.rows[keep[ds.rows]]
    return train, val


def validate(
    params,
    dataset: pairs_lib.PairDataset | pairs_lib.MixedPairs,
    model_config: DITConfig,
    n_pairs: int,
    batch_size: int = 8,
) -> dict[str, float]:
    """Mean isotropic errors on the first ``n_pairs`` validation pairs, two ways:

    * ``rotation_error`` (degrees) / ``translation_error``: full inference, ``register`` with its
      ``n_iters`` iterations, GMCCE included -- what a user gets;
    * ``network_rotation_error`` / ``network_translation_error``: one soft-mode iteration, the network's own
      estimate. On clean pairs GMCCE registers well even with untrained features, so this is the figure that
      shows what training changed, and the one the best checkpoint is chosen by;
    * ``network_match_accuracy``: the share of source points whose most similar target point lies within
      :data:`dit_jax.losses.MATCH_RADIUS` of its true position (the discrimination loss's labels), from the
      same soft iteration.

    For :class:`~dit_jax.data.pairs.MixedPairs`, each setting's ``n_pairs`` are measured (keys
    ``SETTING/...``, full inference with that setting's GMCCE threshold, passed as an array so that settings
    of one cloud size share one compiled program) and the plain keys are the means over the settings.
    Batches are always ``batch_size`` pairs (the last one filled up with pairs already counted), so one
    program serves every batch.
    """
    if isinstance(dataset, pairs_lib.MixedPairs):
        out = {}
        for setting in dataset.datasets:
            threshold = np.float32(configs.GMCCE_THRESHOLDS[setting])
            errors = _validation_errors(
                params,
                functools.partial(dataset.setting_batch, setting),
                min(n_pairs, len(dataset)),
                model_config,
                batch_size,
                threshold,
            )
            out.update({f"{setting}/{k}": v for k, v in errors.items()})
        for key in [k for k in out if k.startswith(f"{dataset.settings[0]}/")]:
            name = key.split("/", 1)[1]
            out[name] = float(np.mean([out[f"{s}/{name}"] for s in dataset.datasets]))
        return out
    return _validation_errors(params, dataset.batch, min(n_pairs, len(dataset)), model_config, batch_size)


#: :func:`dit_jax.losses.match_labels` of a batch, one compiled program (validation runs outside a jit).
_batch_match_labels = jax.jit(jax.vmap(losses.match_labels))


def _validation_errors(
    params,
    batch_of: Callable[[np.ndarray], dict],
    n: int,
    model_config: DITConfig,
    batch_size: int,
    gmcce_threshold: np.ndarray | None = None,
) -> dict[str, float]:
    """:func:`validate`'s figures for pairs ``batch_of(indices)``, indices in ``range(n)``."""
    errors: dict[str, list] = {
        k: []
        for k in (
            "rotation_error",
            "translation_error",
            "network_rotation_error",
            "network_translation_error",
            "network_match_accuracy",
        )
    }
    size = min(batch_size, n)
    for start in range(0, n, size):
        real = min(size, n - start)
        b = batch_of(np.arange(start, start + size) % n)
        src, tgt = jnp.asarray(b["src"]), jnp.asarray(b["tgt"])
        # One program for both figures: the first iteration's increment is the network's own estimate.
        rotation, translation, extras = model.register(params, src, tgt, model_config, gmcce_threshold)
        first = {
            "": (rotation, translation),
            "network_": (extras["step_rotation"][:, 0], extras["step_translation"][:, 0]),
        }
        for prefix, (r, t) in first.items():
            errors[prefix + "rotation_error"].append(np.asarray(metrics.rotation_error_deg(r, b["R"]))[:real])
            errors[prefix + "translation_error"].append(np.asarray(metrics.translation_error(t, b["t"]))[:real])
        labels = _batch_match_labels(
            src, tgt, extras["step_correspondences"][:, 0], jnp.asarray(b["R"]), jnp.asarray(b["t"])
        )
        errors["network_match_accuracy"].append(np.asarray(labels)[:real].reshape(-1))
    return {k: float(np.mean(np.concatenate(v))) for k, v in errors.items()}


# ------------------------------------------------------------------------------------------ checkpoints


class TrainCheckpointError(RuntimeError):
    """The working directory's checkpoints cannot be resumed: damaged, or made by another config."""


def _managers(workdir: str, keep: int):
    workdir = os.path.abspath(workdir)
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False)
    last = ocp.CheckpointManager(os.path.join(workdir, "checkpoints"), options=options, item_names=("state", "meta"))
    best_options = ocp.CheckpointManagerOptions(max_to_keep=1, create=True, enable_async_checkpointing=False)
    best = ocp.CheckpointManager(os.path.join(workdir, "best"), options=best_options, item_names=("state", "meta"))
    return last, best


def _save(manager, state: TrainState, meta: dict) -> None:
    host_state = jax.device_get(state)
    manager.save(
        int(host_state.step),
        args=ocp.args.Composite(state=ocp.args.StandardSave(host_state), meta=ocp.args.JsonSave(meta)),
        force=True,
    )
    manager.wait_until_finished()


def _restore(manager, step: int, abstract: TrainState, config: TrainConfig) -> tuple[TrainState, dict]:
    where = os.path.join(str(manager.directory), str(step))
    try:
        meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta
    except Exception as err:
        raise TrainCheckpointError(
            f"{where}: checkpoint metadata unreadable ({type(err).__name__}); "
            "the checkpoint is damaged -- delete it to resume from an earlier one"
        ) from None
    saved = TrainConfig.from_json(meta["train_config"])
    if saved.model_config() != config.model_config():
        raise TrainCheckpointError(
            f"{where}: made for model {saved.model_config()}, not {config.model_config()}; use another --workdir"
        )
    try:
        state = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract))).state
    except Exception as err:
        # A state saved with the optimiser's state per parameter array (before it was one vector) holds the
        # params this run expects but not its optimiser state: the weights can still start a run.
        hint = (
            "; a checkpoint with the optimiser's state per parameter array (saved before it became one "
            "vector) does not resume: start a run from its weights (training.export_params, then "
            "--config.init_from)"
            if "'opt_state'" in str(err)
            else ""
        )
        raise TrainCheckpointError(
            f"{where}: train state does not restore ({type(err).__name__}: "
            f"{str(err).splitlines()[0][:200] if str(err) else ''}){hint}"
        ) from None
    return state, meta


def export_params(workdir: str, out_dir: str, *, latest: bool = False) -> str:
    """Writes the best (else the latest) params of a training run as a model checkpoint
    (:mod:`dit_jax.checkpoint`), the format ``evaluate.py`` and the registration API read. ``latest``: the
    last checkpoint's params instead of the best (the end of a run whose best came early)."""
    from dit_jax import checkpoint

    workdir = os.path.abspath(workdir)
    for sub in ("checkpoints",) if latest else ("best", "checkpoints"):
        path = os.path.join(workdir, sub)
        if not os.path.isdir(path):
            continue
        manager = ocp.CheckpointManager(path, item_names=("state", "meta"))
        step = manager.latest_step()
        if step is None:
            continue
        meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta
        config = TrainConfig.from_json(meta["train_config"])
        raw = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore())).state
        extra = {
            "step": int(step),
            "chosen_by": sub,
            "n_points": config.n_points,
            "setting": config.setting,
            "data": config.data_dir or "embedded",
            "unseen": config.unseen,
            "variant": config.variant,
            "train_config": config.to_json(),
        }
        return checkpoint.save(out_dir, raw["params"], config.model_config(), overwrite=True, extra=extra)
    raise TrainCheckpointError(f"{workdir}: no checkpoints to export")


# ------------------------------------------------------------------------------------------ curves


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


# ------------------------------------------------------------------------------------------ the loop


def _append_jsonl(path: str, record: dict) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")


def _truncate_log(path: str, after_step: int) -> None:
    """Drops log lines past ``after_step`` (written by a run that was killed before its next checkpoint)."""
    if not os.path.exists(path):
        return
    with open(path) as f:
        lines = [line for line in f if line.strip() and json.loads(line).get("step", 0) <= after_step]
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.writelines(lines)
    os.replace(tmp, path)


def _initialise_from(state: TrainState, path: str, optimizer: optax.GradientTransformation) -> TrainState:
    """``state`` with the params of the model checkpoint at ``path`` and a fresh optimiser state."""
    from dit_jax import checkpoint

    params, _ = checkpoint.restore(path)
    shapes = lambda tree: jax.tree.map(lambda a: tuple(a.shape), tree)
    if shapes(params) != shapes(state.params):
        # A run of more PFT layers starts from a shallower network grown in depth (same outputs).
        try:
            params = {**params, "pft": pft.deepen(params["pft"], state.params["pft"])}
        except (KeyError, ValueError):
            pass
    if shapes(params) != shapes(state.params):
        raise ValueError(f"init_from {path}: its network does not have this run's shape (model config)")
    params = jax.tree.map(jnp.asarray, params)
    return state.replace(params=params, opt_state=optimizer.init(_flat(params)))


def train(
    config: TrainConfig, workdir: str, *, resume: bool = False, prepared_dir: str | None = None, progress: bool = True
) -> dict:
    """Trains DIT; returns the final validation metrics and where the results are.

    Writes to ``workdir``: ``checkpoints/`` (the last ``keep``), ``best/`` (lowest validation rotation
    error of the network alone, see :func:`validate`), ``metrics.jsonl``, ``train_config.json`` and, at the end, ``model/`` (the best params as a model
    checkpoint for ``evaluate.py``).

    In a multi-process run (:func:`initialize_distributed`) every process calls this with the same arguments
    and ``workdir`` (a shared file system); they train one model and save checkpoints together (orbax), and
    process 0 alone writes the log and the config.

    Args:
      resume: continue from the latest checkpoint in ``workdir`` (step, optimiser, RNG and data order
        exactly). Without it, a ``workdir`` that holds checkpoints is refused rather than overwritten.
    """
    workdir = os.path.abspath(workdir)  # orbax needs absolute paths
    os.makedirs(workdir, exist_ok=True)
    model_config = config.model_config()
    mesh = make_mesh()
    n_dev = mesh.devices.size
    if config.batch_size % n_dev:
        raise ValueError(f"batch_size {config.batch_size} is not divisible by the {n_dev} devices")

    train_ds, val_ds = make_datasets(config, prepared_dir, progress and is_primary())
    steps_per_epoch = len(train_ds) // config.batch_size
    if steps_per_epoch == 0:
        raise ValueError(f"{len(train_ds)} training pairs are fewer than one batch of {config.batch_size}")
    total_steps = steps_per_epoch * config.epochs
    if config.max_steps:
        total_steps = min(total_steps, config.max_steps)
    optimizer = make_optimizer(config, total_steps)
    last_mgr, best_mgr = _managers(workdir, config.keep)
    log_path = os.path.join(workdir, "metrics.jsonl")
    primary = is_primary()
    log = (lambda record: _append_jsonl(log_path, record)) if primary else (lambda record: None)

    best_val = math.inf
    latest = last_mgr.latest_step()
    if latest is not None:
        if not resume:
            raise TrainCheckpointError(
                f"{workdir} already holds checkpoints (step {latest}); pass --resume to "
                "continue, or choose a new --workdir"
            )
        # The state's shapes suffice to restore it: no fresh parameters are computed (or compiled) to be
        # overwritten, and a checkpoint of another model is refused before anything is compiled.
        abstract = jax.eval_shape(lambda: init_state(config, optimizer))
        state, meta = _restore(last_mgr, latest, abstract, config)
        best_val = meta.get("best_val", math.inf)
        if primary:
            _truncate_log(log_path, latest)
    else:
        state = init_state(config, optimizer)
        if config.init_from:
            state = _initialise_from(state, config.init_from, optimizer)
        if primary:
            _truncate_log(log_path, -1)
            with open(os.path.join(workdir, "train_config.json"), "w") as f:
                json.dump(config.to_json(), f, indent=2)
    state = replicate(state, mesh)
    step_fn = make_train_step(config, optimizer, mesh)

    def meta(step):
        return {
            "train_config": config.to_json(),
            "step": step,
            "best_val": best_val,
            "steps_per_epoch": steps_per_epoch,
        }

    start = int(state.step)
    bar = None
    if progress and primary:
        from tqdm.auto import tqdm

        bar = tqdm(total=total_steps, initial=start, desc="train", unit="step", dynamic_ncols=True)

    def batches_from(step: int) -> Iterator[tuple[int, dict]]:
        epoch, offset = divmod(step, steps_per_epoch)
        while step < total_steps:
            for b in prefetch.batches(train_ds, config.batch_size, epoch=epoch, start_batch=offset):
                yield epoch, b
                step += 1
                if step >= total_steps:
                    return
            epoch, offset = epoch + 1, 0

    val_metrics = {}

    def run_validation(step: int, epoch: int) -> None:
        nonlocal val_metrics, best_val
        # Through the host onto this process's first device, once per validation (not per batch): the
        # registration program is the one a single-device run compiles (and finds in the compilation cache),
        # whatever the mesh.
        params = jax.device_put(jax.device_get(state.params), jax.local_devices()[0])
        val_metrics = validate(params, val_ds, model_config, config.val_pairs)
        log({"step": step, "epoch": epoch, "split": "val", **val_metrics})
        line = (
            f"step {step}: validation rotation error {val_metrics['rotation_error']:.5f} deg "
            f"(network alone {val_metrics['network_rotation_error']:.3f}, match accuracy "
            f"{val_metrics['network_match_accuracy']:.3f}), translation error "
            f"{val_metrics['translation_error']:.5f} ({val_metrics['network_translation_error']:.4f})"
        )
        if bar is not None:
            bar.write(line)
        elif primary:
            print(line, flush=True)
        if val_metrics["network_rotation_error"] < best_val:
            best_val = val_metrics["network_rotation_error"]
            _save(best_mgr, state, meta(step))

    if start == 0 and config.validate_at_start:
        run_validation(0, 0)  # where training starts from: the first point of every curve
    t_last = time.time()
    step = start
    for epoch, batch in batches_from(start):
        state, out = step_fn(state, shard_batch(batch, mesh))
        step += 1
        if step % config.log_every == 0 or step == total_steps:
            out = {k: float(v) for k, v in jax.device_get(out).items()}
            now = time.time()
            record = {
                "step": step,
                "epoch": epoch,
                "split": "train",
                "skipped": int(state.skipped),
                "lr": float(lr_schedule(config, total_steps)(step - 1)),
                **out,
                "seconds_per_step": (now - t_last) / config.log_every,
            }
            t_last = now
            log(record)
            if bar is not None:
                bar.set_postfix(
                    loss=f"{out['loss']:.3f}",
                    disc=f"{out['discrimination']:.3f}",
                    acc=f"{out['match_accuracy']:.2f}",
                    rot=f"{out['rotation_error']:.1f}",
                    trans=f"{out['translation_error']:.3f}",
                    refresh=False,
                )
        if bar is not None:
            bar.update(1)
        if step % config.eval_every == 0 or step == total_steps:
            run_validation(step, epoch)
        if step % config.ckpt_every == 0 or step == total_steps:
            _save(last_mgr, state, meta(step))
    if bar is not None:
        bar.close()
    last_mgr.close()
    best_mgr.close()
    result = {
        "step": step,
        "total_steps": total_steps,
        "skipped": int(state.skipped),
        "val": val_metrics,
        "best_val_network_rotation_error": best_val,
        "workdir": os.path.abspath(workdir),
        "processes": jax.process_count(),
        "devices": n_dev,
    }
    if step >= total_steps:
        # Every process: orbax's managers synchronise the processes (process 0 writes).
        result["model"] = export_params(workdir, os.path.join(workdir, "model"))
    return result
