"""PSE, the Point cloud Structure Extractor (paper section 3.2; docs/network.md, section 2).

Eight token-transformer layers. Each reads the LFI (local feature integration) of the previous layer's tokens
-- every point's k nearest neighbours' features concatenated, nearest first -- and attends over all points of
the cloud. The eight tokens are concatenated into the point's E-wide structural feature.

All modules act on one cloud, ``points: (N, 3)``; ``jax.vmap`` them over a batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn

from dit_jax.geometry import rigid
from dit_jax.network.configs import PSE_LAYERS, DITConfig
from dit_jax.network.layers import attention, layer_norm, stack_of_layers, torch_dense


def local_feature_integration(features: jax.Array, knn_idx: jax.Array) -> jax.Array:
    """LFI: each point's neighbours' features, neighbour-major (neighbour 0's C values first).

    Args:
      features: (N, C) per-point features.
      knn_idx: (N, k) neighbour indices, nearest first.

    Returns:
      (N, k * C).
    """
    neighbours = rigid.gather_neighbours(features, knn_idx)
    return neighbours.reshape(features.shape[0], -1)


class TokenTransformer(nn.Module):
    """One PSE layer: attention over the cloud's points from the LFI input to a T-wide token.

    Follows the authors' token transformer (docs/network.md, section 2): the attention scale uses the input width D,
    the residual around attention adds the value projection (the input is k T wide, the token T wide), and the
    feed-forward residual starts from the normalised output.
    """

    token_dim: int
    n_heads: int = 4
    attention_chunk: int = 0
    precision: str = "highest"  # of every product, see dit_jax.network.layers.dot_precision

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """x: (N, D) LFI features -> (N, T) tokens."""
        n_points, in_dims = x.shape
        head_dims = self.token_dim // self.n_heads
        u = layer_norm("norm1")(x)
        qkv = torch_dense(3 * self.token_dim, "qkv", use_bias=False, precision=self.precision)(u)
        q, k, v = jnp.split(qkv, 3, axis=-1)
        split = lambda a: a.reshape(n_points, self.n_heads, head_dims)
        scale = (in_dims // self.n_heads) ** -0.5
        mixed = attention(split(q) * scale, split(k), split(v), chunk=self.attention_chunk, precision=self.precision)
        mixed = mixed.reshape(n_points, self.token_dim)
        out = v + torch_dense(self.token_dim, "proj", precision=self.precision)(mixed)
        z = layer_norm("norm2")(out)
        hidden = nn.gelu(torch_dense(self.token_dim, "fc1", precision=self.precision)(z), approximate=False)
        return z + torch_dense(self.token_dim, "fc2", precision=self.precision)(hidden)


class PSE(nn.Module):
    """Point cloud Structure Extractor: (N, 3) points and their kNN graph -> (N, E) features."""

    config: DITConfig

    @nn.compact
    def __call__(self, points: jax.Array, knn_idx: jax.Array) -> jax.Array:
        """points: (N, 3); knn_idx: (N, k) from :func:`rigid.knn`. Returns (N, E)."""
        c = self.config
        settings = (c.token_dim, c.pse_heads, c.attention_chunk, c.precision)
        lfi = lambda features: local_feature_integration(features, knn_idx)
        first = (nn.remat(TokenTransformer) if c.remat else TokenTransformer)(*settings, name="attention1")
        tokens = first(lfi(points))
        # Layers 2 to 8 all read k T wide inputs: the program holds one scanned layer instead of seven.
        _, later = stack_of_layers(
            self,
            TokenTransformer(*settings, parent=None),
            [f"attention{layer}" for layer in range(2, PSE_LAYERS + 1)],
            tokens,
            lambda layer, features: layer(lfi(features)),
            remat=c.remat,
            collect=True,
        )
        tokens = jnp.concatenate([tokens[None], later])  # (8, N, T), token l of every point
        tokens = jnp.moveaxis(tokens, 0, 1).reshape(points.shape[0], -1)  # (N, 8 T), token l at columns l T...
        # The paper writes ReLU here; the authors' code (and so their weights) use leaky ReLU.
        out = jax.nn.leaky_relu(tokens, negative_slope=0.01)
        return layer_norm("norm")(out)
