"""A run's orbax checkpoints (the last few and the best), and the export of its params as a model."""

from __future__ import annotations

import os

import jax
import jax.flatten_util
import orbax.checkpoint as ocp

from dit_jax.training.config import TrainConfig
from dit_jax.training.step import TrainState


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
    (:mod:`dit_jax.network.checkpoint`), the format ``evaluate.py`` and the registration API read. ``latest``: the
    last checkpoint's params instead of the best (the end of a run whose best came early)."""
    from dit_jax.network import checkpoint

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
