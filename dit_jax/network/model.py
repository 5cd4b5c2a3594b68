"""DIT: PSE, PFT and the head composed, and the iterative registration (docs/network.md, sections 4-10).

The network is a Flax Linen module, :class:`~dit_jax.network.dit.DIT`, acting on one pair of clouds; everything a user calls is a
pure function over explicit ``params``:

* :func:`init` -- fresh parameters for a config;
* :func:`features` -- the network's features of one pair;
* :func:`forward` -- one registration step of one pair (features, then the head);
* :func:`register` -- the whole iterative registration of a batch, one jittable call.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
from flax import linen as nn

from dit_jax.geometry import rigid
from dit_jax.network import dit
from dit_jax.network.configs import DITConfig
from dit_jax.network.head import HeadOutput, head

Params = Any


#: DITConfig fields that change what the network computes but not the parameters it holds: configs that
#: differ only in these initialise through one compiled program. (A field not named here counts as shaping
#: the parameters, so a new one can cost a compilation, never a wrong tree.)
_COMPUTE_ONLY_FIELDS = (
    "n_iters",
    "gmcce_k",
    "gmcce_sharpness",
    "gmcce_threshold",
    "gmcce_min_dist2",
    "gmcce_min_keep",
    "guard_iterations",
    "fitness_radius",
    "temp_factor",
    "dropout",
    "attention_chunk",
    "compute_dtype",
    "precision",
    "remat",
)


def init(key: jax.Array, config: DITConfig, n_points: int | None = None) -> Params:
    """Fresh parameters for ``config`` (PyTorch-like initialisation). The tree does not depend on N.

    Configs that differ only in :data:`_COMPUTE_ONLY_FIELDS` get the same parameters from the same key,
    from one compiled program.
    """
    defaults = DITConfig()
    structure = config.replace(**{name: getattr(defaults, name) for name in _COMPUTE_ONLY_FIELDS})
    return _init(key, structure, n_points or max(config.k, 32))


@functools.partial(jax.jit, static_argnames=("config", "n_points"))
def _init(key: jax.Array, config: DITConfig, n_points: int) -> Params:
    """Jitted: one compiled program (cached on disk like the others) instead of a compilation per operation;
    the values are the same bits either way, and do not depend on ``n_points`` (the points only carry shapes
    through the modules)."""
    points = jax.random.normal(key, (n_points, 3))
    return dit.DIT(config).init(key, points, points)["params"]


def embed(params: Params, points: jax.Array, config: DITConfig, *, encode: bool = False) -> dit.Embedding:
    """The :class:`~dit_jax.network.dit.Embedding` of one cloud, points (N, 3); ``encode`` includes PFT's encoder memory
    (deterministic: for inference, where the target's memory serves every iteration)."""
    return dit.DIT(config).apply({"params": params}, points, encode=encode, method=dit.DIT.embed)


def features(
    params: Params,
    src: jax.Array,
    tgt: jax.Array,
    config: DITConfig,
    *,
    tgt_embedding: dit.Embedding | None = None,
    src_knn: jax.Array | None = None,
    deterministic: bool = True,
    dropout_key: jax.Array | None = None,
) -> tuple[dit.Embedding, dit.Features]:
    """The network's features for one pair: src (N, 3), tgt (M, 3).

    ``tgt_embedding`` reuses a target embedding computed earlier (the target does not move across
    iterations); ``src_knn`` (N, k) the source's kNN graph (a rigid motion keeps it). With
    ``deterministic=False`` PFT's dropout is active and needs ``dropout_key``.
    """

    def run(module: dit.DIT):
        src_emb = module.embed(src, knn_idx=src_knn)
        tgt_emb = tgt_embedding if tgt_embedding is not None else module.embed(tgt)
        return src_emb, module.interact(src_emb, tgt_emb, deterministic)

    rngs = None if dropout_key is None else {"dropout": dropout_key}
    return nn.apply(run, dit.DIT(config))({"params": params}, rngs=rngs)


def forward(
    params: Params,
    src: jax.Array,
    tgt: jax.Array,
    config: DITConfig,
    use_gmcce: bool = False,
    *,
    tgt_embedding: dit.Embedding | None = None,
    src_knn: jax.Array | None = None,
) -> tuple[dit.Features, HeadOutput]:
    """One registration step of one pair (the authors' ``forward``): features, then the head.

    src: (N, 3), tgt: (M, 3). Returns the :class:`~dit_jax.network.dit.Features` and the X-to-Y :class:`HeadOutput`.
    ``tgt_embedding`` and ``src_knn``: see :func:`features`.
    """
    _, feats = features(params, src, tgt, config, tgt_embedding=tgt_embedding, src_knn=src_knn)
    return feats, head(src, tgt, feats.scores, feats.temperature, config, use_gmcce)


def _check_inputs(src: jax.Array, tgt: jax.Array, config: DITConfig) -> None:
    for name, cloud in (("src", src), ("tgt", tgt)):
        if cloud.ndim != 3 or cloud.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (B, N, 3), got {tuple(cloud.shape)}")
        if not jnp.issubdtype(cloud.dtype, jnp.floating):
            raise ValueError(f"{name} must be floating point, got {cloud.dtype}")
        if cloud.shape[1] < config.min_points:
            raise ValueError(
                f"{name} has {cloud.shape[1]} points; this config needs at least "
                f"{config.min_points} (k={config.k}, gmcce_k={config.gmcce_k})"
            )
    if src.shape[0] != tgt.shape[0]:
        raise ValueError(f"src and tgt batch sizes differ: {src.shape[0]} vs {tgt.shape[0]}")


def _register_one(
    params: Params, src: jax.Array, tgt: jax.Array, config: DITConfig, gmcce_threshold: jax.Array | None = None
):
    """The iterative registration of one pair (docs/network.md, section 10).

    Computed once, not per iteration: the target's kNN graph, PSE, positional encoding and encoder memory
    (the target does not move) and the source's kNN graph (moving it rigidly keeps its distances). All
    iterations run as one ``lax.scan`` (the head's mode picked by ``lax.cond``: soft first, GMCCE after):
    one compiled body whose buffers every iteration reuses, where unrolled iterations let XLA keep several
    iterations' activations alive at once (paper config, 8192 points, XLA's temporaries: 3.6 GB for three
    scanned iterations against 5.7 GB for two unrolled ones).
    """
    tgt_embedding = embed(params, tgt, config, encode=True)
    src_knn = rigid.knn(src, config.k)
    radius = config.fitness_radius * rigid.spacing(tgt)

    def iteration(carry, index):
        rotation, translation, moved, cost, last = carry
        _, feats = features(params, moved, tgt, config, tgt_embedding=tgt_embedding, src_knn=src_knn)
        run_head = lambda use_gmcce: head(
            moved, tgt, feats.scores, feats.temperature, config, use_gmcce, gmcce_threshold
        )
        out = jax.lax.cond(index >= 1, lambda: run_head(True), lambda: run_head(False))
        new_moved = rigid.apply_transform(out.rotation, out.translation, moved)
        if config.guard_iterations:
            new_cost = rigid.alignment_cost(new_moved, tgt, radius)
            accept = (index == 0) | (new_cost <= cost)
        else:  # the authors' iterations: every update kept, no cost to compute
            new_cost, accept = cost, jnp.asarray(True)
        new_rotation, new_translation = rigid.compose(out.rotation, out.translation, rotation, translation)
        keep = lambda new, old: jnp.where(accept, new, old)
        matches = (out.correspondences, out.weights)
        carry = (
            keep(new_rotation, rotation),
            keep(new_translation, translation),
            keep(new_moved, moved),
            keep(new_cost, cost),
            jax.tree.map(keep, matches, last),
        )
        record = (
            out.rotation,
            out.translation,
            feats.temperature,
            out.gmcce_fallback,
            out.soft_weights,
            accept,
            out.correspondences,
        )
        return carry, record

    n_src = src.shape[0]
    start = (
        jnp.eye(3, dtype=src.dtype),
        jnp.zeros(3, dtype=src.dtype),
        src,
        jnp.asarray(2.0, src.dtype),
        (jnp.zeros(n_src, jnp.int32), jnp.zeros(n_src, src.dtype)),
    )
    carry, records = jax.lax.scan(iteration, start, jnp.arange(config.n_iters))
    rotation, translation, moved, _, (correspondences, weights) = carry
    step_r, step_t, temperature, fallback, soft_weights, accepted, step_matches = records
    extras = {
        "step_rotation": step_r,  # (n_iters, 3, 3), each iteration's own increment
        "step_translation": step_t,  # (n_iters, 3)
        "temperature": temperature,  # (n_iters,)
        "gmcce_fallback": fallback,  # (n_iters,) bool
        "accepted": accepted,  # (n_iters,) bool: the iteration's update was kept (see guard_iterations)
        # (n_iters, N) each iteration's matches into tgt; the first iteration's increment and matches are the
        # network's own estimate (soft mode from the identity), what a one-iteration config returns
        "step_correspondences": step_matches,
        "correspondences": correspondences,  # (N,) the last kept iteration's matches into tgt
        "weights": weights,  # (N,) its Procrustes weights
        "inlier_ratio": jnp.mean((weights > 0.5).astype(src.dtype))
        if config.n_iters > 1
        else jnp.mean(soft_weights[-1]),
        "fitness": rigid.fitness(
            moved, tgt, radius
        ),  # () share of the moved source within fitness_radius spacings of the target
    }
    return rotation, translation, extras


#: N * M above which the pairs of a batch go one at a time on every backend (memory of one pair).
_MAP_PAIRS_ABOVE = 2048 * 2048


@functools.partial(jax.jit, static_argnames=("config",))
def register(
    params: Params, src: jax.Array, tgt: jax.Array, config: DITConfig, gmcce_threshold: jax.Array | None = None
):
    """Estimates the rigid motion mapping each source cloud onto its target.

    ``n_iters`` iterations: the first in soft mode, the rest in GMCCE mode; each re-runs the network on the
    moved source and composes its increment (docs/network.md, section 10). Jitted with ``config`` static; it also
    nests inside a caller's ``jax.jit`` or ``jax.vmap``. The pairs of a batch are vmapped on accelerators and
    mapped one after the other (``lax.map``) on CPU and for clouds above about 2048 points, where
    that is faster and keeps memory at one pair's; the results are the same either way.

    Args:
      params: the model's parameters (from :func:`init`, a checkpoint or the weight converter).
      src: (B, N, 3) source clouds.
      tgt: (B, M, 3) target clouds; M may differ from N.
      config: the :class:`DITConfig` the params were made for.
      gmcce_threshold: (B,) each pair's GMCCE threshold, in place of ``config.gmcce_threshold``: pairs of
        settings with different thresholds then run in one compiled program.

    Returns:
      ``(R, t, extras)`` with R (B, 3, 3), t (B, 3) such that ``tgt ~ src @ R^T + t``, and ``extras``: a dict of
      per-pair arrays ``step_rotation`` (B, n_iters, 3, 3), ``step_translation`` (B, n_iters, 3),
      ``temperature`` (B, n_iters), ``gmcce_fallback`` (B, n_iters) bool, ``correspondences`` (B, N) int32,
      ``weights`` (B, N) and ``inlier_ratio`` (B,) (the fraction of GMCCE inliers in the last kept iteration),
      ``accepted`` (B, n_iters) bool (every iteration, unless ``guard_iterations`` refused it) and
      ``fitness`` (B,) (:func:`dit_jax.geometry.rigid.fitness` of the final estimate).
    """
    _check_inputs(src, tgt, config)
    chex.assert_rank([src, tgt], 3)
    if gmcce_threshold is not None:
        gmcce_threshold = jnp.broadcast_to(jnp.asarray(gmcce_threshold, src.dtype), src.shape[:1])
    if src.shape[0] == 1:
        # The same computation without the batch axis: XLA's CPU buffer assignment keeps ~5x more memory
        # alive for a vmapped batch of one (5.5 GB instead of 1.0 GB for one iteration at 8192 points).
        threshold = None if gmcce_threshold is None else gmcce_threshold[0]
        return jax.tree.map(lambda a: a[None], _register_one(params, src[0], tgt[0], config, threshold))
    one = lambda pair: _register_one(params, pair[0], pair[1], config, *pair[2:])
    pairs = (src, tgt) if gmcce_threshold is None else (src, tgt, gmcce_threshold)
    large = src.shape[1] * tgt.shape[1] > _MAP_PAIRS_ABOVE
    if large or jax.default_backend() == "cpu":
        # One pair at a time: memory stays that of one pair, and on CPU it is faster than the vmapped
        # batch (the matmuls of one pair already fill the cores, and the batched ones pay for transposes).
        return jax.lax.map(one, pairs)
    return jax.vmap(one)(pairs)


class Iterations(NamedTuple):
    """What training needs of each iteration of one pair, stacked over iterations (leading axis I)."""

    rotation: jax.Array  # (I, 3, 3) composed estimate after iteration i, source to target
    translation: jax.Array  # (I, 3)
    rotation_ab: jax.Array  # (I, 3, 3) iteration i's own increment, source to target
    translation_ab: jax.Array  # (I, 3)
    rotation_ba: jax.Array  # (I, 3, 3) iteration i's reverse estimate, target to moved source
    translation_ba: jax.Array  # (I, 3)
    soft_weights: jax.Array  # (I, N) max_j softmax(temperature S)_ij
    correspondences: jax.Array  # (I, N) int32 argmax_j S_ij
    temperature: jax.Array  # (I,)
    soft_targets: jax.Array  # (I, N, 3) softmax(temperature S) Y: where each source point's soft match lies


def _soft_pose(src, tgt, scores, temperature, differentiable: bool):
    """Soft-mode pose of one direction. ``differentiable``: Procrustes on the soft targets P Y with the soft
    weights, gradients flowing through it; otherwise the authors' hard matches with detached weights.
    Returns the pose, the soft weights (N,), the hard matches (N,) and the soft targets P Y (N, 3)."""
    probs = jax.nn.softmax(temperature * scores, axis=-1)
    weights = jnp.max(probs, axis=-1)
    matches = jnp.argmax(probs, axis=-1).astype(jnp.int32)
    soft_targets = jnp.matmul(probs, tgt, precision=jax.lax.Precision.HIGHEST)
    if differentiable:
        rotation, translation = rigid.weighted_procrustes(src, soft_targets, weights)
    else:
        rotation, translation = jax.lax.stop_gradient(rigid.weighted_procrustes(src, tgt[matches], weights))
    return rotation, translation, weights, matches, soft_targets


def unroll(
    params: Params,
    src: jax.Array,
    tgt: jax.Array,
    config: DITConfig,
    n_iters: int,
    *,
    differentiable: bool = False,
    dropout_key: jax.Array | None = None,
) -> Iterations:
    """The training-time iterations of one pair (docs/network.md, sections 10-11): soft mode, both directions.

    Each iteration runs the network on the moved source and estimates source-to-target and
    target-to-source motions (the latter for the cycle loss). The source moves by the detached estimate, so
    gradients do not cross iterations. ``dropout_key`` turns PFT's dropout on.

    Args:
      src: (N, 3); tgt: (M, 3).
      n_iters: iterations (the authors train with 2).
      differentiable: see :func:`_soft_pose`.
    """
    tgt_embedding = embed(params, tgt, config)  # no memory: dropout draws a fresh encoder mask per iteration
    src_knn = rigid.knn(src, config.k)

    # A scan, not a Python loop: the same arithmetic, and the train step's program holds one copy of the
    # network whatever the number of iterations, so it compiles sooner.
    def iteration(carry, index):
        rotation, translation, moved = carry
        key = None if dropout_key is None else jax.random.fold_in(dropout_key, index)
        _, feats = features(
            params,
            moved,
            tgt,
            config,
            tgt_embedding=tgt_embedding,
            src_knn=src_knn,
            deterministic=key is None,
            dropout_key=key,
        )
        r_ab, t_ab, weights, matches, soft_targets = _soft_pose(
            moved, tgt, feats.scores, feats.temperature, differentiable
        )
        r_ba, t_ba, *_ = _soft_pose(tgt, moved, feats.scores.T, feats.temperature, differentiable)
        rotation, translation = rigid.compose(r_ab, t_ab, rotation, translation)
        moved = rigid.apply_transform(jax.lax.stop_gradient(r_ab), jax.lax.stop_gradient(t_ab), moved)
        record = Iterations(
            rotation, translation, r_ab, t_ab, r_ba, t_ba, weights, matches, feats.temperature, soft_targets
        )
        return (rotation, translation, moved), record

    start = (jnp.eye(3, dtype=src.dtype), jnp.zeros(3, dtype=src.dtype), src)
    if n_iters == 1:  # the same record without a scan, whose autodiff costs tracing and compile time
        _, record = iteration(start, jnp.asarray(0))
        return jax.tree.map(lambda a: a[None], record)
    _, records = jax.lax.scan(iteration, start, jnp.arange(n_iters))
    return records
