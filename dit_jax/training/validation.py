"""Training and validation pairs of a run, and the validation of its params."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from dit_jax.data import mixed
from dit_jax.data import pairs as pairs_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.evaluators import metrics
from dit_jax.network import configs, losses, model
from dit_jax.network.configs import DITConfig
from dit_jax.training.config import TrainConfig


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
    :class:`~dit_jax.data.pairs.PairDataset`, or two :class:`~dit_jax.data.mixed.MixedPairs` with
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
        train = mixed.MixedPairs(train_shapes, train_config, config.settings, **thinning)
        val = mixed.MixedPairs(val_shapes, val_config, tuple(dict.fromkeys(config.settings)), **thinning)
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
    dataset: pairs_lib.PairDataset | mixed.MixedPairs,
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
      :data:`dit_jax.network.losses.MATCH_RADIUS` of its true position (the discrimination loss's labels), from the
      same soft iteration.

    For :class:`~dit_jax.data.mixed.MixedPairs`, each setting's ``n_pairs`` are measured (keys
    ``SETTING/...``, full inference with that setting's GMCCE threshold, passed as an array so that settings
    of one cloud size share one compiled program) and the plain keys are the means over the settings.
    Batches are always ``batch_size`` pairs (the last one filled up with pairs already counted), so one
    program serves every batch.
    """
    if isinstance(dataset, mixed.MixedPairs):
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


#: :func:`dit_jax.network.losses.match_labels` of a batch, one compiled program (validation runs outside a jit).
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
