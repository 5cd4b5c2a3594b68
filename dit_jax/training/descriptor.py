"""Training the learned descriptor (:mod:`dit_jax.features.network`) on real rooms: ``python train.py
--config configs/features.py``.

Each step draws a few benchmark pairs of the training scenes and, from each, keypoints of the source whose true
place lies next to a target keypoint (:mod:`dit_jax.training.descriptor_data`). The loss is InfoNCE both ways:
a source keypoint's descriptor should lie nearer its own target keypoint than the other drawn ones (the
pair's other matches and keypoints drawn at random), and the reverse; target keypoints next to the true place
are not counted as wrong. Turns need no augmentation: the input does not change when a scan turns.

``holdout`` names a scene left out of training and validated on (the honest measure); without it every scene
trains and validation reads the training scenes. A run is resumable: optimiser, step and the data's order come
back from the last orbax checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from dit_jax.features import network
from dit_jax.training import descriptor_data as data_lib


@dataclasses.dataclass(frozen=True)
class DescriptorTrainConfig:
    """A descriptor training run's recipe (``configs/features.py``).

    Attributes:
      descriptor: the network (:class:`dit_jax.features.network.DescriptorConfig`).
      data_dir: a folder of 3DMatch scenes (each with its ``3DMatch/`` and ``3DLoMatch/`` lists).
      holdout: the scene left out of training and validated on; "" trains on every scene.
      steps: optimiser steps; lr, weight_decay: AdamW's, the rate falling to 5 % along a cosine.
      pairs, anchors, negatives: per step, pairs drawn, matching keypoints per pair, and keypoints of each
        target drawn at random besides.
      temperature: InfoNCE's, on cosine similarities.
      positive_voxels: keypoints match within this many voxels; near_voxels: target keypoints this close to
        the true place are not negatives.
      max_fragments: the first this many fragments of each scene only (0: all); for tests.
      seed: params and the data's order; log_every, eval_every, ckpt_every: steps between log lines,
        validations and checkpoints (all also at the end).
    """

    descriptor: network.DescriptorConfig = dataclasses.field(default_factory=network.DescriptorConfig)
    data_dir: str = ""
    holdout: str = ""
    steps: int = 4000
    lr: float = 1e-3
    weight_decay: float = 1e-4
    pairs: int = 4
    anchors: int = 128
    negatives: int = 1024
    temperature: float = 0.05
    positive_voxels: float = 0.75
    near_voxels: float = 2.0
    max_fragments: int = 0
    seed: int = 0
    log_every: int = 50
    eval_every: int = 1000
    ckpt_every: int = 500

    def to_json(self) -> dict:
        return {"kind": "descriptor", **dataclasses.asdict(self)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> DescriptorTrainConfig:
        d = {k: v for k, v in d.items() if k != "kind"}
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown DescriptorTrainConfig fields: {', '.join(unknown)}")
        d["descriptor"] = network.DescriptorConfig(**dict(d.get("descriptor", {})))
        return cls(**d)

    def to_config_dict(self):
        from ml_collections import ConfigDict

        return ConfigDict(self.to_json())

    @classmethod
    def from_config_dict(cls, config) -> DescriptorTrainConfig:
        return cls.from_json(config.to_dict())


def info_nce(source: jax.Array, target: jax.Array, near: jax.Array, temperature: float) -> tuple[jax.Array, jax.Array]:
    """InfoNCE both ways over descriptors source (P, A, D) and target (P, A + G, D) whose first A rows match
    the source rows in order; ``near`` (P, A, A + G) marks target rows not counted against a source row.
    Returns (loss, share of source rows whose nearest target row is their match)."""
    labels = jnp.broadcast_to(jnp.arange(source.shape[1]), source.shape[:2])
    forward = jnp.einsum("pad,pbd->pab", source, target) / temperature
    forward = jnp.where(near, -1e9, forward)
    anchors = source.shape[1]
    backward = jnp.einsum("pad,pbd->pab", target[:, :anchors], source) / temperature
    backward = jnp.where(jnp.swapaxes(near[:, :, :anchors], 1, 2), -1e9, backward)
    loss = (
        optax.softmax_cross_entropy_with_integer_labels(forward, labels).mean()
        + optax.softmax_cross_entropy_with_integer_labels(backward, labels).mean()
    ) / 2
    return loss, jnp.mean(jnp.argmax(forward, axis=-1) == labels)


def make_optimizer(config: DescriptorTrainConfig) -> optax.GradientTransformation:
    schedule = optax.cosine_decay_schedule(config.lr, max(config.steps, 1), alpha=0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=config.weight_decay))


def make_step(config: DescriptorTrainConfig, optimizer: optax.GradientTransformation):
    """A jitted ``(params, opt_state, batch) -> (params, opt_state, loss, accuracy)``."""
    model = network.LocalDescriptor(config.descriptor)

    def loss_fn(params, batch: data_lib.Batch):
        source, target = model.apply(params, batch.source), model.apply(params, batch.target)
        return info_nce(source, target, batch.near, config.temperature)

    @jax.jit
    def step(params, opt_state, batch):
        (loss, accuracy), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, batch)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, accuracy

    return step


def validate(describe, scenes: list[data_lib.Scene]) -> dict:
    """Inlier ratio and feature-match recall (:mod:`dit_jax.evaluators.descriptors`) of ``describe`` (a
    :class:`Fragment` -> (N, D) descriptors) over every pair of ``scenes``, per list: {"3DMatch": {...}, ...}."""
    from dit_jax.evaluators import descriptors as quality

    found: dict[str, list] = {}
    for scene in scenes:
        described = [describe(f) if len(f.points) else None for f in scene.fragments]
        for pair in scene.pairs:
            s, t = described[pair.source], described[pair.target]
            if s is None or t is None or len(t) < 2:
                continue
            source, target = scene.fragments[pair.source], scene.fragments[pair.target]
            found.setdefault(pair.listed, []).append(
                quality.match_quality(source.points, s, target.points, t, pair.rotation, pair.translation)
            )
    return {listed: quality.summary(q) for listed, q in sorted(found.items())}


def load_scenes(config: DescriptorTrainConfig) -> tuple[list[data_lib.Scene], list[data_lib.Scene]]:
    """(training scenes, validation scenes) of ``config``'s folder."""
    if not config.data_dir:
        raise ValueError("set --config.data_dir to a folder of 3DMatch scenes")
    names = data_lib.scene_names(config.data_dir)
    if config.holdout and config.holdout not in names:
        raise ValueError(f"holdout {config.holdout!r} is not a scene of {config.data_dir} ({', '.join(names)})")
    if len(names) - bool(config.holdout) < 1:
        raise ValueError(f"{config.data_dir}: no scene to train on")
    folder = pathlib.Path(config.data_dir)
    load = lambda n: data_lib.load_scene(folder / n, config.positive_voxels, config.max_fragments)
    training = [load(n) for n in names if n != config.holdout]
    return training, ([load(config.holdout)] if config.holdout else training)


def _append(path: str, record: dict) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")


def _checkpoints(workdir: str):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True, enable_async_checkpointing=False)
    return ocp, ocp.CheckpointManager(
        os.path.join(workdir, "checkpoints"), options=options, item_names=("state", "meta")
    )


def _describer(config: DescriptorTrainConfig, params):
    descriptor = network.Descriptor(params, config.descriptor, {})
    return lambda fragment: network.embed(descriptor, fragment.histograms)


def train(config: DescriptorTrainConfig, workdir: str, *, resume: bool = False, progress: bool = True) -> dict:
    """Trains the descriptor; returns the final validation beside FPFH's and the histograms' and where the
    weights are. Writes to ``workdir``: ``train_config.json``, ``metrics.jsonl`` (appended, never cut; a
    resumed run's records follow the old ones, the last record of a step is the one that stands),
    ``checkpoints/``, ``curves.png`` and, at the end, ``descriptor/`` (:func:`dit_jax.features.network.load`
    reads it; ``--descriptor DIR`` matches by it)."""
    workdir = os.path.abspath(workdir)
    os.makedirs(workdir, exist_ok=True)
    ocp, manager = _checkpoints(workdir)
    optimizer = make_optimizer(config)
    params, opt_state, start = _start(config, workdir, manager, optimizer, resume)
    training, validation = load_scenes(config)
    metrics = os.path.join(workdir, "metrics.jsonl")
    measured = {name: validate(lambda f, n=name: getattr(f, n), validation) for name in ("fpfh", "histograms")}
    step_fn = make_step(config, optimizer)
    bar = _progress(config.steps, start) if progress else None
    started = time.perf_counter()
    final = None
    for step in range(start, config.steps):
        rng = np.random.default_rng([config.seed, step])  # the data's order survives a resume
        batch = data_lib.draw_batch(training, rng, config.pairs, config.anchors, config.negatives, config.near_voxels)
        params, opt_state, loss, accuracy = step_fn(params, opt_state, batch)
        done = step + 1
        if done % config.log_every == 0 or done == config.steps:
            record = {"split": "train", "step": done, "loss": float(loss), "accuracy": float(accuracy)}
            _append(metrics, record | {"seconds": time.perf_counter() - started})
        if done % config.eval_every == 0 or done == config.steps:
            final = validate(_describer(config, params), validation)
            _append(metrics, {"split": "val", "step": done, "learned": final, **measured})
        if done % config.ckpt_every == 0 or done == config.steps:
            state = {"params": params, "opt_state": opt_state}
            meta = {"train_config": config.to_json()}
            save = ocp.args.Composite(state=ocp.args.StandardSave(jax.device_get(state)), meta=ocp.args.JsonSave(meta))
            manager.save(done, args=save, force=True)
            manager.wait_until_finished()
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{float(loss):.3f}")
    if bar is not None:
        bar.close()
    if final is None:  # resumed at the end: the weights as they stand
        final = validate(_describer(config, params), validation)
    extra = {
        "scenes": [s.name for s in training],
        "steps": config.steps,
        "validation": final,
        "holdout": config.holdout,
    }
    out = network.save(
        os.path.join(workdir, "descriptor"), network.Descriptor(params, config.descriptor, extra), overwrite=True
    )
    plot_curves(workdir, os.path.join(workdir, "curves.png"))
    validated_on = config.holdout or "the training scenes"
    return {"workdir": workdir, "descriptor": out, "validated_on": validated_on, "learned": final, **measured}


def _start(config: DescriptorTrainConfig, workdir: str, manager, optimizer, resume: bool):
    """(params, optimiser state, step) to start from: the last checkpoint's with ``resume``, else fresh ones
    (and the run's ``train_config.json``). A workdir with checkpoints is not started afresh, nor resumed by
    another config."""
    import orbax.checkpoint as ocp

    from dit_jax.training.checkpoints import TrainCheckpointError

    latest = manager.latest_step()
    if latest is not None and not resume:
        raise TrainCheckpointError(f"{workdir} holds checkpoints; pass --resume or choose another --workdir")
    params = network.init(config.descriptor, config.seed)
    opt_state = optimizer.init(params)
    if latest is None:
        with open(os.path.join(workdir, "train_config.json"), "w") as f:
            json.dump(config.to_json(), f, indent=1)
        return params, opt_state, 0
    meta = manager.restore(latest, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta
    if DescriptorTrainConfig.from_json(meta["train_config"]) != config:
        raise TrainCheckpointError(f"{workdir}: its checkpoints were made by another config; use another --workdir")
    abstract = {"params": params, "opt_state": opt_state}
    state = manager.restore(latest, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract))).state
    return state["params"], state["opt_state"], int(latest)


def _progress(total: int, start: int):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=start, desc="train descriptor", unit="step", dynamic_ncols=True)


def plot_curves(workdir: str, path: str) -> None:
    """The run's training loss and validation inlier ratios per list (FPFH's and the histograms' dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        records = [json.loads(line) for line in f if line.strip()]
    train = {r["step"]: r for r in records if r["split"] == "train"}  # a step's last record stands
    val = {r["step"]: r for r in records if r["split"] == "val"}
    fig, (loss_axes, ratio_axes) = plt.subplots(1, 2, figsize=(9, 3.6))
    steps = sorted(train)
    loss_axes.plot(steps, [train[s]["loss"] for s in steps])
    loss_axes.set(title="training loss (InfoNCE)", xlabel="step")
    steps = sorted(val)
    for k, listed in enumerate(sorted(val[steps[-1]]["learned"]) if steps else ()):
        colour = f"C{k}"
        ratio_axes.plot(
            steps,
            [val[s]["learned"][listed]["inlier_ratio"] for s in steps],
            "o-",
            color=colour,
            label=f"learned, {listed}",
        )
        for name, style in (("histograms", "--"), ("fpfh", ":")):
            ratio_axes.axhline(
                val[steps[-1]][name][listed]["inlier_ratio"], ls=style, color=colour, label=f"{name}, {listed}"
            )
    ratio_axes.set(title="validation inlier ratio", xlabel="step")
    ratio_axes.legend(fontsize=6)
    for axes in (loss_axes, ratio_axes):
        axes.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
