"""The train step: optimiser, the loss and its gradients over a batch, and the device mesh it runs on."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dit_jax.evaluators import metrics
from dit_jax.network import losses, model
from dit_jax.network.configs import DITConfig
from dit_jax.training.config import TrainConfig


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
