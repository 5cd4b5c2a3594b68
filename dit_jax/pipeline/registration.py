"""Registering your own point clouds: load a model once, then ``register(src, tgt)`` in the caller's units.

    from dit_jax import registration
    model = registration.load()                      # the shipped weights; or load("runs/x/model"), load("a.pth")
    result = model.register(src_points, tgt_points)  # (N, 3), (M, 3) arrays in any units
    moved = result.apply(src_points)                 # result.matrix is the 4x4 transform

:meth:`Registrar.register` runs the pipeline of :mod:`dit_jax.pipeline.stages` (sample and normalise, network,
refine, verdict) on a batch of one pair, with the :class:`~dit_jax.pipeline.settings.InferenceSettings` the checkpoint
stores; keyword arguments of :func:`load` change any of them.
"""

from __future__ import annotations

import importlib.resources
import os

import jax

from dit_jax.network.configs import DITConfig
from dit_jax.pipeline import stages
from dit_jax.pipeline.result import Result
from dit_jax.pipeline.settings import MODEL_OVERRIDES, InferenceSettings

#: Where the weights that ship with the package live (their runs: MODEL_CARD.md).
SHIPPED_WEIGHTS = "network/weights/dit-cpu-modelnet40"
#: Where a checkpoint's ``extra`` record keeps its :class:`InferenceSettings`.
SETTINGS_KEY = "inference_settings"


class Registrar:
    """A model loaded once, registering pairs of clouds of any size, scale and offset.

    Args:
      params, config: the model (see :func:`load` to read them from a checkpoint).
      settings: the pipeline's settings (:class:`~dit_jax.pipeline.settings.InferenceSettings`).
      **changes: fields of ``settings`` to change, e.g. ``refine="none"``.

    Attributes:
      settings: the settings in force; config: the model config the network runs (``checkpoint_config`` with
        the settings' overrides applied, once); checkpoint_config: the model config as the checkpoint stores
        it; params: the network's parameters.

    Settings change in one of two ways: for the registrar (:func:`load`'s changes, or :meth:`replace`), or for
    one call (:meth:`register`'s and :meth:`register_pairs`' changes), which cannot touch the network's own
    settings (:data:`~dit_jax.pipeline.settings.MODEL_OVERRIDES`).
    """

    def __init__(self, params, config: DITConfig, settings: InferenceSettings | None = None, **changes):
        self.settings = (settings or InferenceSettings()).replace(**changes)
        self.checkpoint_config = config
        self.config = self.settings.model_config(config)  # what the network runs
        self.params = jax.device_put(params)  # one transfer for the tree, where jnp.asarray runs a program a leaf
        need = self.config.min_points
        if self.settings.n_points < need:
            raise ValueError(f"n_points={self.settings.n_points} is below the model's minimum {need}")

    def register(self, src, tgt, **changes) -> Result:
        """Registers ``src`` (N, 3) onto ``tgt`` (M, 3), both in the caller's units.

        ``changes``: settings for this call only, e.g. ``refine="none"`` (one of
        :data:`~dit_jax.pipeline.settings.REFINEMENTS`) or ``rotation_search=True``; None keeps the registrar's. Raises
        :class:`~dit_jax.pipeline.sampling.InputError` naming the cloud DIT cannot register."""
        return self.register_pairs([(src, tgt)], batch_size=1, **changes)[0]

    def register_pairs(self, pairs, *, batch_size: int = 8, on_pair=None, **changes) -> list[Result]:
        """:meth:`register` for many ``(src, tgt)`` pairs, batched through the network
        (:func:`dit_jax.pipeline.stages.register_pairs`); ``on_pair(count)`` as pairs finish."""
        changes = {name: value for name, value in changes.items() if value is not None}
        network_changes = sorted(set(changes) & set(MODEL_OVERRIDES))
        if network_changes:
            raise ValueError(
                f"{', '.join(network_changes)} change the network itself: set them with load(...) or replace(...)"
            )
        settings = self.settings.replace(**changes) if changes else self.settings
        return stages.register_pairs(self.params, self.config, settings, pairs, batch_size=batch_size, on_pair=on_pair)

    def prepare_scans(self, clouds) -> stages.ScanSet:
        """``clouds`` (K of (N_k, 3)) checked, with each one's features computed once, for
        :meth:`register_scan_pairs` (:func:`dit_jax.pipeline.stages.prepare_scans`)."""
        return stages.prepare_scans(self.config, self.settings, clouds)

    def register_scan_pairs(self, scans, pairs, *, batch_size: int = 8, on_pair=None) -> list[Result]:
        """:meth:`register_pairs` for index ``pairs`` ``(source, target)`` of one set of scans (a scene's):
        ``scans`` from :meth:`prepare_scans`, or the clouds themselves (prepared here)
        (:func:`dit_jax.pipeline.stages.register_scan_pairs`)."""
        if not isinstance(scans, stages.ScanSet):
            scans = self.prepare_scans(scans)
        return stages.register_scan_pairs(
            self.params, self.config, self.settings, scans, pairs, batch_size=batch_size, on_pair=on_pair
        )

    def replace(self, *, config: DITConfig | None = None, **changes) -> Registrar:
        """A registrar of the same weights with ``changes`` to the settings (and ``config`` in place of the
        checkpoint's model config, e.g. another ``compute_dtype``); the overrides apply once, to the checkpoint's."""
        return Registrar(self.params, config or self.checkpoint_config, self.settings, **changes)


def shipped_weights() -> str:
    """Path of the weights that ship with the package (a checkpoint directory)."""
    return os.fspath(importlib.resources.files("dit_jax") / SHIPPED_WEIGHTS)


def settings_from_extra(extra: dict) -> InferenceSettings:
    """The :class:`InferenceSettings` a checkpoint's ``extra`` record stores (:data:`SETTINGS_KEY`); the
    defaults where it stores none."""
    return InferenceSettings.from_dict(extra.get(SETTINGS_KEY) or {})


def load(
    checkpoint: str | os.PathLike | None = None, *, compile_cache: str | os.PathLike | bool = True, **changes
) -> Registrar:
    """A :class:`Registrar` from an orbax checkpoint directory, the authors' ``.pth`` weights, or (None) the
    shipped weights, with the inference settings the checkpoint stores; ``changes`` override any of them.

    ``compile_cache``: where compiled programs (and a plain copy of the weights) are kept between processes,
    so that the next process's first registration loads them instead of compiling (:mod:`dit_jax.network.compile_cache`):
    True, the default directory (``$DIT_JAX_COMPILE_CACHE``, else ``~/.cache/dit-jax/xla``; the variable set
    to ``off`` turns it off); a directory; or False, off. The process's first choice stands (a command-line
    tool's flags, or the first ``load``)."""
    from dit_jax.network import checkpoint as ckpt_lib
    from dit_jax.network import compile_cache as cache_lib

    if not cache_lib.chosen():
        chosen = {True: cache_lib.default_dir(), False: None}.get(compile_cache, compile_cache)
        cache_lib.enable(None if chosen is None else os.fspath(chosen))

    path = os.fspath(checkpoint) if checkpoint is not None else shipped_weights()
    if checkpoint is None and not os.path.isdir(path):
        raise ckpt_lib.CheckpointError(f"no checkpoint given and the shipped weights are missing ({path})")
    if os.path.isfile(path) and path.endswith((".pth", ".pt", ".t7")):
        from dit_jax.network import convert

        state_dict = convert.load_pth(path)
        config = convert.infer_config(state_dict)
        params, extra = convert.from_torch_state_dict(state_dict, config), {}
    else:
        params, config = ckpt_lib.restore(path)
        extra = ckpt_lib.read_extra(path)
    return Registrar(params, config, settings_from_extra(extra), **changes)
