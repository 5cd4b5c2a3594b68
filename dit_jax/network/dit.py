"""The Deep Interaction Transformer as a Flax Linen module, :class:`DIT`, on one pair of clouds: PSE and the
positional encoding of each cloud (:class:`Embedding`), PFT across the two, squeeze-and-excitation, the
temperature and the similarity (:class:`Features`); docs/network.md, sections 4-8. Call it through the pure
functions of :mod:`dit_jax.network.model`."""

from __future__ import annotations

from typing import NamedTuple

import jax
from flax import linen as nn

from dit_jax.geometry import rigid
from dit_jax.network.configs import DITConfig
from dit_jax.network.head import TemperatureNet, similarity
from dit_jax.network.pft import PFT, PositionalEncoding, SqueezeExcitation
from dit_jax.network.pse import PSE


class Embedding(NamedTuple):
    """What DIT computes from one cloud alone: independent of the other cloud and of the pose estimate
    of the other, so the target's is computed once per registration."""

    knn_idx: jax.Array  # (N, k)
    pse: jax.Array  # (N, E), PSE(X)
    positional: jax.Array  # (N, E), P(X)
    memory: jax.Array | None = None  # (N, E), PFT's encoder applied to PSE(X) + P(X); None: not computed yet


class Features(NamedTuple):
    """The network's outputs for one pair (N source and M target points)."""

    src_p: jax.Array  # (N, E) PFT output for the source, phi(F_Y, F_X)
    tgt_p: jax.Array  # (M, E) phi(F_X, F_Y)
    phi_src: jax.Array  # (N, E) Phi_X = SE(PSE(X) + src_p)
    phi_tgt: jax.Array  # (M, E)
    temperature: jax.Array  # ()
    scores: jax.Array  # (N, M) S


class DIT(nn.Module):
    """The Deep Interaction Transformer's network, on one pair of clouds."""

    config: DITConfig

    def setup(self):
        c = self.config
        self.pse = PSE(c)
        self.positional_encoding = PositionalEncoding(c.emb_dims, c.pe_expansion, c.precision)
        self.pft = PFT(c)
        self.se = SqueezeExcitation(c.emb_dims, c.se_reduction, c.precision)
        self.temp_net = TemperatureNet(c.temp_hidden, c.temp_factor, c.precision)

    def embed(
        self, points: jax.Array, knn_idx: jax.Array | None = None, encode: bool = False, deterministic: bool = True
    ) -> Embedding:
        """points: (N, 3) -> the cloud's :class:`Embedding`.

        ``knn_idx`` (N, k) reuses a kNN graph computed earlier: a rigid motion keeps every distance, so a
        moving cloud's graph is that of its first pose. ``encode`` also runs PFT's encoder (the memory).
        """
        if knn_idx is None:
            knn_idx = rigid.knn(points, self.config.k)
        pse, positional = self.pse(points, knn_idx), self.positional_encoding(points)
        memory = self.pft.encode(pse + positional, deterministic) if encode else None
        return Embedding(knn_idx, pse, positional, memory)

    def interact(self, src: Embedding, tgt: Embedding, deterministic: bool = True) -> Features:
        """PFT across the two clouds, squeeze-and-excitation, temperature and similarity.

        The same as ``self.pft(F_X, F_Y)``, with each cloud's encoder memory taken from its embedding where
        it was computed before.
        """
        f_x, f_y = src.pse + src.positional, tgt.pse + tgt.positional
        memory_x = src.memory if src.memory is not None else self.pft.encode(f_x, deterministic)
        memory_y = tgt.memory if tgt.memory is not None else self.pft.encode(f_y, deterministic)
        src_p = self.pft.decode(f_x, memory_y, deterministic)
        tgt_p = self.pft.decode(f_y, memory_x, deterministic)
        phi_src = self.se(src.pse + src_p)
        phi_tgt = self.se(tgt.pse + tgt_p)
        temperature = self.temp_net(phi_src, phi_tgt)
        scores = similarity(phi_src, phi_tgt, self.config.precision)
        return Features(src_p, tgt_p, phi_src, phi_tgt, temperature, scores)

    def __call__(self, src: jax.Array, tgt: jax.Array, deterministic: bool = True) -> Features:
        return self.interact(self.embed(src), self.embed(tgt), deterministic)
