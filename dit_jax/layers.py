"""Small building blocks shared by PSE, PFT and the temperature net."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn


def layer_norm(name: str, eps: float = 1e-5) -> nn.LayerNorm:
    """PyTorch's ``nn.LayerNorm``: biased variance, ``eps`` inside the square root, scale and bias.

    Flax's fast variance (E[x^2] - E[x]^2) loses digits when the mean is large; the two-pass form matches
    PyTorch to float rounding.
    """
    return nn.LayerNorm(epsilon=eps, use_fast_variance=False, name=name)


class AnnotatedLayerNorm(nn.Module):
    """LN* of the authors' PFT (SPEC.md section 4): ``a_2 (x - mean) / (std + eps) + b_2``.

    ``std`` is the unbiased (n - 1) standard deviation and ``eps`` (1e-6) is added to it, not to the
    variance: both differ from a standard LayerNorm and both matter for matching their numbers.
    """

    eps: float = 1e-6

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        width = x.shape[-1]
        scale = self.param("a_2", nn.initializers.ones, (width,), jnp.float32)
        bias = self.param("b_2", nn.initializers.zeros, (width,), jnp.float32)
        mean = jnp.mean(x, axis=-1, keepdims=True)
        centred = x - mean
        std = jnp.sqrt(jnp.sum(centred * centred, axis=-1, keepdims=True) / (width - 1))
        return scale * centred / (std + self.eps) + bias


def torch_dense(features: int, name: str, use_bias: bool = True) -> nn.Dense:
    """A Dense layer whose kernel starts like PyTorch's ``nn.Linear`` weight: U(+-1/sqrt(fan_in)).

    (variance scaling 1/3 with a uniform law has exactly that bound.) Biases start at zero. Kernels are
    stored (in, out), the transpose of PyTorch's (out, in).
    """
    return nn.Dense(
        features,
        use_bias=use_bias,
        kernel_init=nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform"),
        name=name,
    )
