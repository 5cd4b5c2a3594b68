"""The training loop behind ``python train.py``: :func:`train`, resumable from its checkpoints."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Iterator
from typing import NamedTuple

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax

from dit_jax.data import prefetch
from dit_jax.network import pft
from dit_jax.training import precision as precision_lib
from dit_jax.training import step as step_lib
from dit_jax.training.checkpoints import TrainCheckpointError, _managers, _restore, _save, export_params
from dit_jax.training.config import TrainConfig
from dit_jax.training.validation import make_datasets, validate


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


def _initialise_from(
    state: step_lib.TrainState, path: str, optimizer: optax.GradientTransformation
) -> step_lib.TrainState:
    """``state`` with the params of the model checkpoint at ``path`` and a fresh optimiser state."""
    from dit_jax.network import checkpoint

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
    return state.replace(params=params, opt_state=optimizer.init(step_lib._flat(params)))


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
    plan = _plan(config, prepared_dir, progress)
    config = plan.config
    last_mgr, best_mgr = _managers(workdir, config.keep)
    primary = step_lib.is_primary()
    log_path = os.path.join(workdir, "metrics.jsonl")
    log = (lambda record: _append_jsonl(log_path, record)) if primary else (lambda record: None)
    state, best_val = _starting_state(config, plan.optimizer, workdir, last_mgr, resume=resume, primary=primary)
    state = step_lib.replicate(state, mesh := plan.mesh)
    step_fn = step_lib.make_train_step(config, plan.optimizer, mesh)
    start = int(state.step)
    bar = _progress_bar(plan.total_steps, start) if progress and primary else None
    validation = _Validation(plan, best_mgr, log, bar, primary, best_val)
    if start == 0 and config.validate_at_start:
        validation.run(state, 0, 0)  # where training starts from: the first point of every curve
    t_last = time.time()
    step = start
    for epoch, batch in _batches_from(plan, start):
        state, out = step_fn(state, step_lib.shard_batch(batch, mesh))
        step += 1
        if step % config.log_every == 0 or step == plan.total_steps:
            out = {k: float(v) for k, v in jax.device_get(out).items()}
            now = time.time()
            log(_train_record(plan, state, out, step, epoch, (now - t_last) / config.log_every))
            t_last = now
            if bar is not None:
                _show(bar, out)
        if bar is not None:
            bar.update(1)
        if step % config.eval_every == 0 or step == plan.total_steps:
            validation.run(state, step, epoch)
        if step % config.ckpt_every == 0 or step == plan.total_steps:
            _save(last_mgr, state, validation.meta(step))
    if bar is not None:
        bar.close()
    last_mgr.close()
    best_mgr.close()
    result = {
        "step": step,
        "total_steps": plan.total_steps,
        "skipped": int(state.skipped),
        "val": validation.metrics,
        "best_val_network_rotation_error": validation.best,
        "workdir": os.path.abspath(workdir),
        "processes": jax.process_count(),
        "devices": mesh.devices.size,
    }
    if step >= plan.total_steps:
        # Every process: orbax's managers synchronise the processes (process 0 writes).
        result["model"] = export_params(workdir, os.path.join(workdir, "model"))
    return result


class _Plan(NamedTuple):
    """What a run fixes before its first step: its config (``train_precision`` resolved), the devices' mesh,
    the data, the optimiser and the step counts."""

    config: TrainConfig
    mesh: jax.sharding.Mesh
    train_ds: object
    val_ds: object
    optimizer: optax.GradientTransformation
    steps_per_epoch: int
    total_steps: int


def _plan(config: TrainConfig, prepared_dir: str | None, progress: bool) -> _Plan:
    """The :class:`_Plan` of a run of ``config``; raises ValueError where the batch does not fit the devices
    or the data."""
    mesh = step_lib.make_mesh()
    if config.batch_size % mesh.devices.size:
        raise ValueError(f"batch_size {config.batch_size} is not divisible by the {mesh.devices.size} devices")
    train_ds, val_ds = make_datasets(config, prepared_dir, progress and step_lib.is_primary())
    steps_per_epoch = len(train_ds) // config.batch_size
    if steps_per_epoch == 0:
        raise ValueError(f"{len(train_ds)} training pairs are fewer than one batch of {config.batch_size}")
    total_steps = steps_per_epoch * config.epochs
    if config.max_steps:
        total_steps = min(total_steps, config.max_steps)
    optimizer = step_lib.make_optimizer(config, total_steps)
    if config.train_precision == "auto":
        choice = precision_lib.choose(config, optimizer, mesh, train_ds.batch(np.arange(config.batch_size)))
        config = dataclasses.replace(config, train_precision=choice.precision)  # what train_config.json records
        if step_lib.is_primary():
            print(choice.describe(), flush=True)
    return _Plan(config, mesh, train_ds, val_ds, optimizer, steps_per_epoch, total_steps)


def _batches_from(plan: _Plan, step: int) -> Iterator[tuple[int, dict]]:
    """(epoch, batch) from training step ``step`` on, to the run's last step, in the data's exact order."""
    epoch, offset = divmod(step, plan.steps_per_epoch)
    while step < plan.total_steps:
        for b in prefetch.batches(plan.train_ds, plan.config.batch_size, epoch=epoch, start_batch=offset):
            yield epoch, b
            step += 1
            if step >= plan.total_steps:
                return
        epoch, offset = epoch + 1, 0


class _Validation:
    """The run's validations: each logs its metrics, shows its line and saves the best network so far."""

    def __init__(self, plan: _Plan, best_mgr, log, bar, primary: bool, best: float):
        self.plan, self.best_mgr, self.log, self.bar, self.primary = plan, best_mgr, log, bar, primary
        self.best = best
        self.metrics: dict = {}
        self.model_config = plan.config.model_config()

    def meta(self, step: int) -> dict:
        """What a checkpoint at ``step`` records beside the state."""
        config = self.plan.config
        return {"train_config": config.to_json(), "step": step, "best_val": self.best,
                "steps_per_epoch": self.plan.steps_per_epoch}  # fmt: skip

    def run(self, state: step_lib.TrainState, step: int, epoch: int) -> None:
        # Through the host onto this process's first device, once per validation (not per batch): the
        # registration program is the one a single-device run compiles (and finds in the compilation cache),
        # whatever the mesh.
        params = jax.device_put(jax.device_get(state.params), jax.local_devices()[0])
        self.metrics = validate(params, self.plan.val_ds, self.model_config, self.plan.config.val_pairs)
        self.log({"step": step, "epoch": epoch, "split": "val", **self.metrics})
        line = _validation_line(step, self.metrics)
        if self.bar is not None:
            self.bar.write(line)
        elif self.primary:
            print(line, flush=True)
        if self.metrics["network_rotation_error"] < self.best:
            self.best = self.metrics["network_rotation_error"]
            _save(self.best_mgr, state, self.meta(step))


def _progress_bar(total_steps: int, start: int):
    from tqdm.auto import tqdm

    return tqdm(total=total_steps, initial=start, desc="train", unit="step", dynamic_ncols=True)


def _train_record(plan: _Plan, state: step_lib.TrainState, out: dict, step: int, epoch: int, seconds: float) -> dict:
    """The log's line for a training step: the step's losses and metrics (``out``), the learning rate and the
    mean ``seconds`` per step since the last line."""
    lr = float(step_lib.lr_schedule(plan.config, plan.total_steps)(step - 1))
    return {"step": step, "epoch": epoch, "split": "train", "skipped": int(state.skipped), "lr": lr, **out,
            "seconds_per_step": seconds}  # fmt: skip


def _show(bar, out: dict) -> None:
    """The progress bar's figures after a logged step."""
    bar.set_postfix(
        loss=f"{out['loss']:.3f}",
        disc=f"{out['discrimination']:.3f}",
        acc=f"{out['match_accuracy']:.2f}",
        rot=f"{out['rotation_error']:.1f}",
        trans=f"{out['translation_error']:.3f}",
        refresh=False,
    )


def _starting_state(
    config: TrainConfig, optimizer: optax.GradientTransformation, workdir: str, last_mgr, *, resume: bool, primary: bool
) -> tuple[step_lib.TrainState, float]:
    """The state a run starts from, and its best validation so far: the latest checkpoint in ``workdir``
    where ``resume`` (refused without it), else fresh parameters or ``config.init_from``'s. The log is cut
    back to the checkpoint's step (or emptied), and a fresh run writes its ``train_config.json``."""
    log_path = os.path.join(workdir, "metrics.jsonl")
    latest = last_mgr.latest_step()
    if latest is not None:
        if not resume:
            raise TrainCheckpointError(
                f"{workdir} already holds checkpoints (step {latest}); pass --resume to "
                "continue, or choose a new --workdir"
            )
        # The state's shapes suffice to restore it: no fresh parameters are computed (or compiled) to be
        # overwritten, and a checkpoint of another model is refused before anything is compiled.
        abstract = jax.eval_shape(lambda: step_lib.init_state(config, optimizer))
        state, meta = _restore(last_mgr, latest, abstract, config)
        if primary:
            _truncate_log(log_path, latest)
        return state, meta.get("best_val", math.inf)
    state = step_lib.init_state(config, optimizer)
    if config.init_from:
        state = _initialise_from(state, config.init_from, optimizer)
    if primary:
        _truncate_log(log_path, -1)
        with open(os.path.join(workdir, "train_config.json"), "w") as f:
            json.dump(config.to_json(), f, indent=2)
    return state, math.inf


def _validation_line(step: int, val_metrics: dict) -> str:
    """A validation's one line for the console."""
    return (
        f"step {step}: validation rotation error {val_metrics['rotation_error']:.5f} deg "
        f"(network alone {val_metrics['network_rotation_error']:.3f}, match accuracy "
        f"{val_metrics['network_match_accuracy']:.3f}), translation error "
        f"{val_metrics['translation_error']:.5f} ({val_metrics['network_translation_error']:.4f})"
    )
