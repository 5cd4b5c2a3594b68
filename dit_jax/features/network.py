"""A learned descriptor of scan keypoints: a small Flax network over each keypoint's joined histograms.

The histograms (:func:`dit_jax.features.descriptors.histograms`: square-rooted FPFH at four radii, 132 numbers)
describe a keypoint's neighbourhood in numbers that do not change when the scan turns; the network re-weighs
and mixes them into ``out`` numbers of unit length, trained (:mod:`dit_jax.training.descriptor`) so that a
keypoint's descriptor lies nearest the descriptor of the same place seen in another scan. It sees only what the
histograms hold, so it keeps their invariance to turns of any size and to the clouds' units; where it fails,
the histograms fail first (docs/features.md).

A :class:`Descriptor` record carries the weights and their :class:`DescriptorConfig`; :func:`save` and
:func:`load` keep both in one orbax directory, and :func:`shipped` loads the weights the package ships
(trained on real rooms, see MODEL_CARD.md). :func:`embed` runs the network in fixed-size chunks: one compiled
program whatever a scan's keypoint count.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

#: How many numbers the joined histograms give a keypoint (four FPFH blocks of 33).
HISTOGRAM_SIZE = 132
#: Keypoints embedded per compiled call: scans are padded to a multiple of it.
CHUNK = 2048
FORMAT = 1
#: Where the shipped weights live inside the package.
SHIPPED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "weights", "descriptor-rooms")


@dataclasses.dataclass(frozen=True)
class DescriptorConfig:
    """The network's shape.

    Attributes:
      width: units of the hidden layers (the first has twice as many).
      out: numbers in a descriptor (unit length).
      histogram_size: numbers in a keypoint's input (:data:`HISTOGRAM_SIZE`).
    """

    width: int = 128
    out: int = 64
    histogram_size: int = HISTOGRAM_SIZE

    def __post_init__(self):
        for name in ("width", "out", "histogram_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DescriptorConfig.{name} must be at least 1, got {getattr(self, name)}")


class LocalDescriptor(nn.Module):
    """histograms (..., H) -> descriptors (..., out) of unit length; a zero input gives a zero descriptor's
    direction-free stand-in (the bias alone), never NaN."""

    config: DescriptorConfig

    @nn.compact
    def __call__(self, histograms: jax.Array) -> jax.Array:
        width = self.config.width
        hidden = nn.gelu(nn.Dense(2 * width, name="mix")(histograms))
        hidden = nn.gelu(nn.Dense(width, name="hidden")(hidden))
        found = nn.Dense(self.config.out, name="project")(hidden)
        return found / jnp.maximum(jnp.linalg.norm(found, axis=-1, keepdims=True), 1e-6)


class Descriptor(NamedTuple):
    """Learned descriptor weights: ``params`` (a Flax tree) for a :class:`LocalDescriptor` of ``config``;
    ``extra``: how they were made (scenes, steps, the validation), as :func:`save` stored it."""

    params: Any
    config: DescriptorConfig
    extra: dict


def init(config: DescriptorConfig, seed: int = 0) -> Any:
    """Fresh params of a :class:`LocalDescriptor` of ``config``."""
    model = LocalDescriptor(config)
    return model.init(jax.random.PRNGKey(seed), jnp.zeros((1, config.histogram_size), jnp.float32))


@functools.partial(jax.jit, static_argnums=1)
def _apply(params: Any, config: DescriptorConfig, histograms: jax.Array) -> jax.Array:
    return LocalDescriptor(config).apply(params, histograms)


def embed(descriptor: Descriptor, histograms: np.ndarray) -> np.ndarray:
    """Descriptors (N, out) float32 of N keypoints' ``histograms`` (N, H), in chunks of :data:`CHUNK`."""
    histograms = np.asarray(histograms, np.float32)
    if histograms.ndim != 2 or histograms.shape[1] != descriptor.config.histogram_size:
        raise ValueError(f"histograms must be (N, {descriptor.config.histogram_size}), got {tuple(histograms.shape)}")
    found = []
    for start in range(0, len(histograms), CHUNK):
        block = histograms[start : start + CHUNK]
        padded = np.zeros((CHUNK, block.shape[1]), np.float32)
        padded[: len(block)] = block
        found.append(np.asarray(_apply(descriptor.params, descriptor.config, padded))[: len(block)])
    out = np.concatenate(found) if found else np.zeros((0, descriptor.config.out), np.float32)
    return np.ascontiguousarray(out, np.float32)


def save(directory: str | os.PathLike, descriptor: Descriptor, *, overwrite: bool = False) -> str:
    """Writes ``descriptor`` to ``directory`` (which must not exist unless ``overwrite``); the absolute path."""
    import orbax.checkpoint as ocp

    path = os.path.abspath(os.fspath(directory))
    if os.path.exists(path) and not overwrite:
        raise FileExistsError(f"{path} already exists; choose a new directory")
    meta = {"format": FORMAT, "descriptor_config": dataclasses.asdict(descriptor.config), "extra": descriptor.extra}
    with ocp.Checkpointer(ocp.CompositeCheckpointHandler()) as checkpointer:
        checkpointer.save(
            path,
            ocp.args.Composite(
                params=ocp.args.StandardSave(jax.device_get(descriptor.params)), config=ocp.args.JsonSave(meta)
            ),
            force=overwrite,
        )
    return path


def load(directory: str | os.PathLike) -> Descriptor:
    """The :class:`Descriptor` :func:`save` wrote to ``directory``; ValueError with one line where it is not one."""
    import orbax.checkpoint as ocp

    path = os.path.abspath(os.fspath(directory))
    try:
        with open(os.path.join(path, "config", "metadata")) as f:
            meta = json.load(f)
        config = DescriptorConfig(**meta["descriptor_config"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a learned descriptor's weights ({type(err).__name__}: {err})") from None
    abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), init(config))
    with ocp.Checkpointer(ocp.CompositeCheckpointHandler()) as checkpointer:
        params = checkpointer.restore(path, ocp.args.Composite(params=ocp.args.StandardRestore(abstract))).params
    return Descriptor(jax.tree.map(np.asarray, params), config, meta.get("extra", {}))


@functools.cache
def _cached(path: str) -> Descriptor:
    return load(path)


def shipped() -> Descriptor:
    """The descriptor weights the package ships, loaded once per process."""
    if not os.path.isdir(SHIPPED):
        raise FileNotFoundError(f"the shipped descriptor weights are missing ({SHIPPED})")
    return _cached(SHIPPED)


def from_path(path: str | os.PathLike | None) -> Descriptor:
    """``shipped()`` for None, else the weights at ``path`` (each loaded once per process)."""
    return shipped() if path is None else _cached(os.path.abspath(os.fspath(path)))
