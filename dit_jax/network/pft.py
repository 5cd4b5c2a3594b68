"""PFT, the Point Feature Transformer (paper section 3.3; docs/network.md, sections 3-5).

Positional encoding of the coordinates, a deep encoder/decoder Transformer that lets each cloud attend to the
other, and squeeze-and-excitation. Everything acts on one pair of clouds, ``(N, E)`` and ``(M, E)`` features.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn

from dit_jax.network.configs import DITConfig
from dit_jax.network.layers import AnnotatedLayerNorm, attention, torch_dense


class PositionalEncoding(nn.Module):
    """P(X) = ReLU(Linear(Sigmoid(Linear(xyz)))), widths 3 -> expansion E -> E."""

    emb_dims: int
    expansion: int
    precision: str = "highest"  # of every product, see dit_jax.network.layers.dot_precision

    @nn.compact
    def __call__(self, points: jax.Array) -> jax.Array:
        """points: (N, 3) -> (N, E)."""
        hidden = jax.nn.sigmoid(torch_dense(self.expansion * self.emb_dims, "fc0", precision=self.precision)(points))
        return jax.nn.relu(torch_dense(self.emb_dims, "fc2", precision=self.precision)(hidden))


class MultiHeadAttention(nn.Module):
    """softmax(Q K^T / sqrt(d)) V over ``n_heads`` heads of d = E / h consecutive channels, then W_o."""

    emb_dims: int
    n_heads: int
    attention_chunk: int = 0  # query rows per block, see :func:`dit_jax.network.layers.attention`
    dtype: str = "float32"  # of the products; parameters and outputs stay float32
    precision: str = "highest"  # of the products, see dit_jax.network.layers.dot_precision

    @nn.compact
    def __call__(self, query: jax.Array, key: jax.Array, value: jax.Array) -> jax.Array:
        """query: (N, E); key, value: (M, E). Returns (N, E)."""
        head_dims = self.emb_dims // self.n_heads
        split = lambda a: a.reshape(a.shape[0], self.n_heads, head_dims)
        dense = lambda name: torch_dense(self.emb_dims, name, dtype=self.dtype, precision=self.precision)
        q, k, v = split(dense("q")(query)), split(dense("k")(key)), split(dense("v")(value))
        mixed = attention(q, k, v, float(head_dims) ** 0.5, chunk=self.attention_chunk, precision=self.precision)
        mixed = mixed.reshape(query.shape[0], self.emb_dims)
        return dense("o")(mixed).astype(jnp.float32)


class FeedForward(nn.Module):
    """w_2(dropout(leaky_relu(w_1 x, 0.2))), widths E -> ff_dims -> E."""

    emb_dims: int
    ff_dims: int
    dropout: float
    dtype: str = "float32"  # of the products; parameters and outputs stay float32
    precision: str = "highest"  # of the products, see dit_jax.network.layers.dot_precision

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        dense = lambda width, name: torch_dense(width, name, dtype=self.dtype, precision=self.precision)
        hidden = jax.nn.leaky_relu(dense(self.ff_dims, "w_1")(x), negative_slope=0.2)
        hidden = nn.Dropout(self.dropout)(hidden, deterministic=deterministic)
        return dense(self.emb_dims, "w_2")(hidden).astype(jnp.float32)


def _residual_attention(c: DITConfig, x: jax.Array, norm: str, name: str, memory: jax.Array | None = None) -> jax.Array:
    """x + Attn(LN*(x), memory), a layer's attention sub-block: x (N, E) attends over ``memory`` (M, E), or
    over its own normalised self where ``memory`` is None; the layer norm is submodule ``norm``, the attention
    submodule ``name``."""
    u = AnnotatedLayerNorm(name=norm)(x)
    memory = u if memory is None else memory
    attention = MultiHeadAttention(c.emb_dims, c.n_heads, c.attention_chunk, c.compute_dtype, c.precision, name=name)
    return x + attention(u, memory, memory)


def _residual_feed_forward(c: DITConfig, x: jax.Array, norm: str, deterministic: bool) -> jax.Array:
    """x + FF(LN*(x)), the last sub-block of every layer, with its layer norm named ``norm``."""
    u = AnnotatedLayerNorm(name=norm)(x)
    feed_forward = FeedForward(c.emb_dims, c.ff_dims, c.dropout, c.compute_dtype, c.precision, name="feed_forward")
    return x + feed_forward(u, deterministic)


class EncoderLayer(nn.Module):
    """x += SelfAttn(LN*(x)); x += FF(LN*(x)) (pre-norm)."""

    config: DITConfig

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        x = _residual_attention(self.config, x, "norm0", "self_attn")
        return _residual_feed_forward(self.config, x, "norm1", deterministic)


class DecoderLayer(nn.Module):
    """Self-attention, cross-attention to the memory, feed-forward; each pre-norm with a residual."""

    config: DITConfig

    @nn.compact
    def __call__(self, x: jax.Array, memory: jax.Array, deterministic: bool = True) -> jax.Array:
        x = _residual_attention(self.config, x, "norm0", "self_attn")
        x = _residual_attention(self.config, x, "norm1", "src_attn", memory)
        return _residual_feed_forward(self.config, x, "norm2", deterministic)


class Encoder(nn.Module):
    config: DITConfig

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        # deterministic (argument 2, counting the module) is a Python bool: static under remat.
        layer = nn.remat(EncoderLayer, static_argnums=(2,)) if self.config.remat else EncoderLayer
        for i in range(self.config.n_blocks):
            x = layer(self.config, name=f"layers_{i}")(x, deterministic)
        return AnnotatedLayerNorm(name="norm")(x)


class Decoder(nn.Module):
    config: DITConfig

    @nn.compact
    def __call__(self, x: jax.Array, memory: jax.Array, deterministic: bool = True) -> jax.Array:
        layer = nn.remat(DecoderLayer, static_argnums=(3,)) if self.config.remat else DecoderLayer
        for i in range(self.config.n_blocks):
            x = layer(self.config, name=f"layers_{i}")(x, memory, deterministic)
        return AnnotatedLayerNorm(name="norm")(x)


class PFT(nn.Module):
    """phi(a, b) = Decoder(b, memory=Encoder(a)), applied in both directions with shared weights.

    Given F_X and F_Y (PSE features plus positional encodings) returns ``(src_p, tgt_p)`` with
    ``tgt_p = phi(F_X, F_Y)`` and ``src_p = phi(F_Y, F_X)``.
    """

    config: DITConfig

    def setup(self):
        self.encoder = Encoder(self.config)
        self.decoder = Decoder(self.config)

    def encode(self, features: jax.Array, deterministic: bool = True) -> jax.Array:
        """The encoder's memory of one cloud, (N, E) -> (N, E); it depends on that cloud alone."""
        return self.encoder(features, deterministic)

    def decode(self, features: jax.Array, memory: jax.Array, deterministic: bool = True) -> jax.Array:
        """Decodes one cloud's features (M, E) against the other's memory (N, E); returns (M, E)."""
        return self.decoder(features, memory, deterministic)

    def phi(self, first: jax.Array, second: jax.Array, deterministic: bool = True) -> jax.Array:
        """Encodes ``first`` (N, E), decodes ``second`` (M, E) against it; returns (M, E)."""
        return self.decode(second, self.encode(first, deterministic), deterministic)

    def __call__(self, f_x: jax.Array, f_y: jax.Array, deterministic: bool = True):
        """f_x: (N, E), f_y: (M, E) -> src_p (N, E), tgt_p (M, E)."""
        return self.phi(f_y, f_x, deterministic), self.phi(f_x, f_y, deterministic)


class SqueezeExcitation(nn.Module):
    """f * sigmoid(W_2 ReLU(W_1 mean_points(f))), per channel, widths E -> E / r -> E, no biases."""

    emb_dims: int
    reduction: int = 16
    precision: str = "highest"  # of the products, see dit_jax.network.layers.dot_precision

    @nn.compact
    def __call__(self, features: jax.Array) -> jax.Array:
        """features: (N, E) -> (N, E)."""
        squeezed = jnp.mean(features, axis=0)
        dense = lambda width, name: torch_dense(width, name, use_bias=False, precision=self.precision)
        hidden = jax.nn.relu(dense(self.emb_dims // self.reduction, "fc0")(squeezed))
        gate = jax.nn.sigmoid(dense(self.emb_dims, "fc2")(hidden))
        return features * gate


#: Each PFT layer's residual outputs: the last product of every branch added to the residual stream.
_RESIDUAL_OUTPUTS = (("self_attn", "o"), ("src_attn", "o"), ("feed_forward", "w_2"))


def deepen(params, fresh):
    """PFT params with more layers that compute what ``params`` computed (growing the network in depth).

    ``params`` is a PFT's parameter tree (``encoder`` and ``decoder``, each ``layers_0`` .. ``layers_{n-1}``
    and ``norm``); ``fresh`` is that of a PFT of the same width with more layers (freshly initialised, say).
    Returns ``fresh`` with the layers and final norms of ``params`` in place of its own, and every layer beyond
    them kept from ``fresh`` with its residual outputs (each attention's ``o`` and the feed-forward's ``w_2``,
    kernels and biases) zeroed. A pre-norm layer whose residual branches end in zeros adds nothing to its
    input, so the deeper network's outputs equal the shallower one's; training then gives the new layers a
    use. Raises ``ValueError`` where ``fresh`` has fewer layers, or other shapes, than ``params``.
    """
    deeper = {}
    for stack in ("encoder", "decoder"):
        old, new = params[stack], fresh[stack]
        if not set(old) <= set(new):
            raise ValueError(f"PFT {stack}: the deeper network lacks {sorted(set(old) - set(new))}")
        grown = dict(old)
        for name in sorted(set(new) - set(old)):
            layer = {branch: dict(values) for branch, values in new[name].items()}
            for branch, product in _RESIDUAL_OUTPUTS:
                if branch in layer:
                    layer[branch][product] = jax.tree.map(jnp.zeros_like, layer[branch][product])
            grown[name] = layer
        shape = lambda tree: jax.tree.map(jnp.shape, tree)
        if shape(grown) != shape(new):
            raise ValueError(f"PFT {stack}: the layers differ in shape, not only in number")
        deeper[stack] = grown
    return deeper
