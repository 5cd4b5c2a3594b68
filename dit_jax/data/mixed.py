"""Pairs read in other ways than one setting at a time: :class:`MixedPairs`, batches drawn from several
settings over the same shapes (training on a mix), and :class:`PairView`, pairs of a dataset or of a stacked
batch, optionally with each pair's clouds swapped."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from dit_jax.data import pairs, views
from dit_jax.data.shapes import Shapes

#: Names the random stream that thins a mix's clouds to one size (see :class:`MixedPairs`).
_THIN_STREAM = 0x7417


class MixedPairs:
    """Pairs of several settings over the same shapes, for training on a mix.

    Each batch comes whole from one setting, chosen at random by the batch's first pair and the epoch, so the
    mix is the same on every run and a resumed run sees the same batches. ``datasets`` maps each setting to
    its :class:`~dit_jax.data.pairs.PairDataset`; list a setting twice in ``settings`` to draw it twice as often.

    With ``one_size`` every cloud of every setting is thinned to :attr:`cloud_points` (``points``, else the
    fewest points any setting's clouds hold) by :func:`~dit_jax.data.views.thin`: all batches then have one shape, so a train step
    compiles once for the whole mix. Without it each setting keeps its own size and compiles its own step,
    unless ``points`` caps it (clouds of more points are thinned to ``points``; a step per size that remains).
    ``sampling="varied"`` thins each cloud by a sampler drawn at random (:data:`~dit_jax.data.views.SAMPLERS`), so that no one
    sampling pattern is learned.
    """

    def __init__(
        self,
        shapes: Shapes,
        config: pairs.PairConfig,
        settings: tuple[str, ...],
        *,
        one_size: bool = False,
        points: int | None = None,
        sampling: str = "uniform",
    ):
        if not settings:
            raise ValueError("MixedPairs needs at least one setting")
        if sampling not in ("uniform", "varied"):
            raise ValueError(f"unknown sampling {sampling!r}; choose uniform or varied")
        self.settings = tuple(settings)
        self.datasets = {s: pairs.PairDataset(shapes, dataclasses.replace(config, setting=s)) for s in self.settings}
        self.config = self.datasets[self.settings[0]].config
        self.shapes = shapes
        self.sampling = sampling
        self._sizes = {s: ds.config.cloud_points(shapes.points.shape[1]) for s, ds in self.datasets.items()}
        limit, which = (min(self._sizes.values()), "fewest") if one_size else (max(self._sizes.values()), "most")
        if points is not None and not 0 < points <= limit:
            raise ValueError(f"points ({points}) must be in 1..{limit}, the {which} points a cloud of this mix holds")
        #: Points in each cloud with ``one_size``; else the cap ``points`` (None: each setting its own size).
        self.cloud_points = points if points is not None or not one_size else limit

    def setting_points(self, setting: str) -> int:
        """Points in each cloud of ``setting``'s batches."""
        own = self._sizes[setting]
        return own if self.cloud_points is None else min(self.cloud_points, own)

    @property
    def rows(self) -> np.ndarray:
        return self.datasets[self.settings[0]].rows

    def __len__(self) -> int:
        return len(self.rows)

    def setting_of(self, indices, epoch: int = 0) -> str:
        """The setting whose pairs the batch ``indices`` gets."""
        first = int(np.asarray(indices).reshape(-1)[0])
        pick = np.random.default_rng([self.config.seed, epoch, first, 0xB1E]).integers(len(self.settings))
        return self.settings[int(pick)]

    def batch(self, indices, epoch: int = 0) -> dict[str, np.ndarray]:
        return self.setting_batch(self.setting_of(indices, epoch), indices, epoch)

    def setting_batch(self, setting: str, indices, epoch: int = 0) -> dict[str, np.ndarray]:
        """Pairs ``indices`` of ``setting``, thinned to :meth:`setting_points`."""
        ds = self.datasets[setting]
        out = ds.batch(indices, epoch)
        if self.cloud_points is None:
            return out
        # A stream of its own per pair: thinning moves none of the pair's other draws.
        return views.thin(
            out,
            self.setting_points(setting),
            [ds._rng(int(n), epoch, _THIN_STREAM) for n in out["index"]],
            self.sampling,
        )


class PairView:
    """Pairs read as a :class:`~dit_jax.data.pairs.PairDataset` is read (``view.batch(indices)``, ``view[n]``), from a dataset or
    from one stacked batch (a dict of arrays with the pairs along axis 0, as :meth:`PairDataset.batch` and
    :func:`dit_jax.training.validation_batches` give); with ``swap`` every pair's clouds trade places, so the
    target is registered onto the source."""

    def __init__(self, source, swap: bool = False):
        self.source = source
        self.swap = swap

    def _out(self, pair: dict) -> dict:
        return pair | {"src": pair["tgt"], "tgt": pair["src"]} if self.swap else pair

    def batch(self, indices) -> dict:
        if isinstance(self.source, Mapping):
            return self._out({k: v[np.asarray(indices)] for k, v in self.source.items()})
        return self._out(self.source.batch(indices))

    def __getitem__(self, n: int) -> dict:
        if isinstance(self.source, Mapping):
            return self._out({k: v[n] for k, v in self.source.items()})
        return self._out(self.source[n])
