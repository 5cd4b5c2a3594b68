"""Shared layers: blocked attention equals attention over all rows, in value and in gradient."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dit_jax import layers


@pytest.mark.parametrize("chunk", [0, 7, 16, 50])
def test_blocked_attention_is_attention(chunk):
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    q = jax.random.normal(keys[0], (50, 4, 8))
    k = jax.random.normal(keys[1], (30, 4, 8))
    v = jax.random.normal(keys[2], (30, 4, 6))
    expected = jnp.einsum("hnm,mhd->nhd", jax.nn.softmax(jnp.einsum("nhd,mhd->hnm", q, k) / 2.0, axis=-1), v)
    out = layers.attention(q, k, v, 2.0, chunk=chunk, precision="highest")
    assert out.shape == (50, 4, 6)
    np.testing.assert_allclose(np.asarray(out), np.asarray(expected), atol=1e-5)
    loss = lambda q, k, v, c: jnp.sum(jnp.sin(layers.attention(q, k, v, 2.0, chunk=c, precision="highest")))
    for a, b in zip(jax.grad(loss, argnums=(0, 1, 2))(q, k, v, 0), jax.grad(loss, argnums=(0, 1, 2))(q, k, v, chunk)):
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
    ours = lambda q, k, v: jnp.sum(weights * jnp.tanh(layers.attention(q, k, v, divisor, chunk=chunk,
                                                                        precision="highest")))
    plain = lambda q, k, v: jnp.sum(weights * jnp.tanh(_plain_attention(q, k, v, divisor)))
    out = layers.attention(q, k, v, divisor, chunk=chunk, precision="highest")
    np.testing.assert_allclose(np.asarray(out), np.asarray(_plain_attention(q, k, v, divisor)), atol=1e-5)
    grads = jax.grad(ours, argnums=(0, 1, 2))(q, k, v)
    expected = jax.grad(plain, argnums=(0, 1, 2))(q, k, v)
    for name, got, want in zip("qkv", grads, expected):
        scale = float(jnp.max(jnp.abs(want)))
        assert scale > 1e-3, name  # a gradient that could be wrong
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=2e-5 * scale, err_msg=name)


def test_bfloat16_attention_gradients_are_bfloat16_and_close():
    q = jax.random.normal(jax.random.PRNGKey(4), (24, 2, 8))
    low = q.astype(jnp.bfloat16)
    grad = lambda x: jax.grad(lambda a: jnp.sum(jnp.sin(layers.attention(a, a, a, 8.0 ** 0.5, precision="highest")
                                                      .astype(jnp.float32))))(x)
    got, exact = grad(low), grad(q)
    assert got.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(got, np.float32), np.asarray(exact), atol=5e-2)


def test_bfloat16_inputs_keep_float32_softmax():
    q = jax.random.normal(jax.random.PRNGKey(1), (20, 2, 8))
    exact = layers.attention(q, q, q, 8.0 ** 0.5, precision="highest")
    low = layers.attention(q.astype(jnp.bfloat16), q.astype(jnp.bfloat16), q.astype(jnp.bfloat16), 8.0 ** 0.5,
                           precision="highest")
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
