"""Shared layers: blocked attention equals attention over all rows, in value and in gradient; a scanned stack
of layers equals the layers applied one by one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen as nn

from dit_jax.network import layers

#: attention as a caller jits it: one compiled program per setting, where op-by-op dispatch would compile
#: each of its operations.
_attention = jax.jit(layers.attention, static_argnames=("divisor", "chunk", "precision"))


@pytest.mark.parametrize("chunk", [0, 7, 16, 50])
def test_blocked_attention_is_attention(chunk):
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    q = jax.random.normal(keys[0], (50, 4, 8))
    k = jax.random.normal(keys[1], (30, 4, 8))
    v = jax.random.normal(keys[2], (30, 4, 6))
    expected = jnp.einsum("hnm,mhd->nhd", jax.nn.softmax(jnp.einsum("nhd,mhd->hnm", q, k) / 2.0, axis=-1), v)
    out = _attention(q, k, v, 2.0, chunk=chunk, precision="highest")
    assert out.shape == (50, 4, 6)
    np.testing.assert_allclose(np.asarray(out), np.asarray(expected), atol=1e-5)
    loss = lambda q, k, v, c: jnp.sum(jnp.sin(layers.attention(q, k, v, 2.0, chunk=c, precision="highest")))
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3)
    for a, b in zip(grad(q, k, v, 0), grad(q, k, v, chunk)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-5)


def _plain_attention(q, k, v, divisor):
    """softmax(q k^T / divisor) v written as the formula, differentiated by JAX itself."""
    logits = jnp.einsum("nhd,mhd->hnm", q, k, precision="highest") / divisor
    return jnp.einsum("hnm,mhd->nhd", jax.nn.softmax(logits, axis=-1), v, precision="highest")


@pytest.mark.parametrize("head_dims", [4, 32])  # PSE's narrow heads and PFT's
@pytest.mark.parametrize("chunk", [0, 7])
def test_attention_gradients_are_those_of_the_formula(head_dims, chunk):
    """The written-out backward pass (softmax recomputed from the log-sum-exp, key-major products) gives
    JAX's own gradients of softmax(q k^T / divisor) v at float32 rounding, in blocks or not."""
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    q = 2.0 * jax.random.normal(keys[0], (40, 4, head_dims))
    k = 2.0 * jax.random.normal(keys[1], (33, 4, head_dims))
    v = jax.random.normal(keys[2], (33, 4, 5))
    weights = jax.random.normal(keys[3], (40, 4, 5))  # a loss whose cotangent differs per output
    divisor = float(head_dims) ** 0.5
    ours = lambda q, k, v: jnp.sum(
        weights * jnp.tanh(layers.attention(q, k, v, divisor, chunk=chunk, precision="highest"))
    )
    plain = lambda q, k, v: jnp.sum(weights * jnp.tanh(_plain_attention(q, k, v, divisor)))
    out = _attention(q, k, v, divisor, chunk=chunk, precision="highest")
    np.testing.assert_allclose(np.asarray(out), np.asarray(_plain_attention(q, k, v, divisor)), atol=1e-5)
    grads = jax.jit(jax.grad(ours, argnums=(0, 1, 2)))(q, k, v)
    expected = jax.jit(jax.grad(plain, argnums=(0, 1, 2)))(q, k, v)
    for name, got, want in zip("qkv", grads, expected):
        scale = float(jnp.max(jnp.abs(want)))
        assert scale > 1e-3, name  # a gradient that could be wrong
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=2e-5 * scale, err_msg=name)


def test_bfloat16_attention_gradients_are_bfloat16_and_close():
    q = jax.random.normal(jax.random.PRNGKey(4), (24, 2, 8))
    low = q.astype(jnp.bfloat16)
    grad = lambda x: jax.grad(
        lambda a: jnp.sum(jnp.sin(layers.attention(a, a, a, 8.0**0.5, precision="highest").astype(jnp.float32)))
    )(x)
    got, exact = grad(low), grad(q)
    assert got.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(got, np.float32), np.asarray(exact), atol=5e-2)


def test_bfloat16_inputs_keep_float32_softmax():
    q = jax.random.normal(jax.random.PRNGKey(1), (20, 2, 8))
    exact = layers.attention(q, q, q, 8.0**0.5, precision="highest")
    low = layers.attention(
        q.astype(jnp.bfloat16), q.astype(jnp.bfloat16), q.astype(jnp.bfloat16), 8.0**0.5, precision="highest"
    )
    assert low.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(low, np.float32), np.asarray(exact), atol=5e-2)


def test_clip_inward_has_the_value_of_clip_and_a_gradient_back_into_range():
    x = jnp.asarray([-2.0, 0.005, 0.5, 3.0, 150.0])
    np.testing.assert_array_equal(np.asarray(layers.clip_inward(x, 0.01, 100.0)), np.asarray(jnp.clip(x, 0.01, 100.0)))
    # Loss -sum(clip): descent raises every value. Below the range that leads back in, so the gradient
    # passes there (jnp.clip passes none); above the range it would lead further out, so none passes.
    up = jax.grad(lambda v: -jnp.sum(layers.clip_inward(v, 0.01, 100.0)))(x)
    np.testing.assert_array_equal(np.asarray(up), [-1.0, -1.0, -1.0, -1.0, 0.0])
    down = jax.grad(lambda v: jnp.sum(layers.clip_inward(v, 0.01, 100.0)))(x)
    np.testing.assert_array_equal(np.asarray(down), [0.0, 0.0, 1.0, 1.0, 1.0])
    assert not np.any(np.asarray(jax.grad(lambda v: -jnp.sum(jnp.clip(v, 0.01, 100.0)))(x))[:2])


class _Layer(nn.Module):
    """A residual dense layer with dropout: the smallest layer with parameters, an input and randomness."""

    @nn.compact
    def __call__(self, x, deterministic=True):
        hidden = nn.Dropout(0.5)(jnp.tanh(nn.Dense(x.shape[-1], name="dense")(x)), deterministic=deterministic)
        return x + hidden


class _Stack(nn.Module):
    remat: bool = False

    @nn.compact
    def __call__(self, x, deterministic=True):
        return layers.stack_of_layers(
            self,
            _Layer(parent=None),
            ["a", "b", "c"],
            x,
            lambda layer, x: layer(x, deterministic),
            remat=self.remat,
            dropout=not deterministic,
            collect=True,
        )


def test_a_stack_of_layers_is_its_layers_applied_in_turn_each_with_its_own_parameters():
    x = jax.random.normal(jax.random.PRNGKey(0), (5, 6))
    params = _Stack().init(jax.random.PRNGKey(1), x)["params"]
    assert sorted(params) == ["a", "b", "c"] and params["a"]["dense"]["kernel"].shape == (6, 6)
    # At initialisation each layer draws its parameters as a submodule of that name would.
    expected = x
    outputs = []
    for name in ("a", "b", "c"):
        expected = _Layer().apply({"params": params[name]}, expected)
        outputs.append(expected)
    last, stacked = _Stack().apply({"params": params}, x)
    np.testing.assert_allclose(np.asarray(last), np.asarray(expected), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(stacked), np.asarray(jnp.stack(outputs)), rtol=1e-6, atol=1e-6)
    # With dropout each layer draws its own mask; rematerialised, the same masks and gradients.
    rngs = {"dropout": jax.random.PRNGKey(2)}
    loss = lambda p, remat: jnp.sum(_Stack(remat).apply({"params": p}, x, False, rngs=rngs)[0] ** 2)
    dropped = np.asarray(_Stack().apply({"params": params}, x, False, rngs=rngs)[1])
    hidden = np.diff(np.concatenate([np.asarray(x)[None], dropped]), axis=0)  # each layer's own branch
    assert (hidden == 0).any() and not np.array_equal(hidden[0] == 0, hidden[1] == 0)
    grads, grads_remat = (jax.grad(loss)(params, remat) for remat in (False, True))
    jax.tree.map(
        lambda g, h: np.testing.assert_allclose(np.asarray(h), np.asarray(g), rtol=1e-5, atol=1e-6), grads, grads_remat
    )
