"""The head's temperature net: the authors' clamp in the forward pass, a gradient that can leave it."""

import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.network.head import TemperatureNet


def _net_at_lower_clamp():
    """A temperature net and input features whose raw output lies below 1 / factor (clamped)."""
    net = TemperatureNet(hidden=16, factor=100.0)
    phi_x = jax.random.normal(jax.random.PRNGKey(0), (32, 24))
    phi_y = jax.random.normal(jax.random.PRNGKey(1), (40, 24))
    for seed in range(20):
        params = net.init(jax.random.PRNGKey(seed), phi_x, phi_y)
        if float(net.apply(params, phi_x, phi_y)) == np.float32(0.01):
            return net, params, phi_x, phi_y
    raise AssertionError("no seed puts the temperature at its lower clamp")


def test_a_clamped_temperature_still_learns_to_rise():
    net, params, phi_x, phi_y = _net_at_lower_clamp()
    temperature = jax.jit(lambda p: net.apply(p, phi_x, phi_y))
    # Any loss that wants a sharper softmax wants a higher temperature; it must reach the net's weights.
    grad = jax.jit(jax.grad(lambda p: -net.apply(p, phi_x, phi_y)))
    descend = jax.jit(lambda p, g: jax.tree.map(lambda a, b: a - 0.05 * jnp.sign(b), p, g))
    grads = grad(params)
    assert max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(grads)) > 0
    stepped = descend(params, grads)
    for _ in range(50):
        if float(temperature(stepped)) > 0.01:
            break
        stepped = descend(stepped, grad(stepped))
    assert float(temperature(stepped)) > 0.01


def test_a_clamped_temperature_is_not_pushed_further_out():
    net, params, phi_x, phi_y = _net_at_lower_clamp()
    grads = jax.grad(lambda p: net.apply(p, phi_x, phi_y))(params)  # wants it lower still: nothing to do
    assert all(float(jnp.max(jnp.abs(g))) == 0.0 for g in jax.tree.leaves(grads))


def test_a_gmcce_threshold_passed_as_an_array_is_the_configs_threshold():
    """``gmcce_threshold`` as an array (how settings with different thresholds share one compiled program)
    gives what the config's own threshold gives, and a threshold the confidences straddle changes the
    weights, so the array is what decides."""
    from dit_jax.network import configs
    from dit_jax.network.head import head

    rng = np.random.default_rng(0)
    src = jnp.asarray(rng.uniform(-1, 1, (40, 3)), jnp.float32)
    tgt = src + jnp.asarray(rng.normal(0, 0.03, (40, 3)), jnp.float32)
    scores = jnp.asarray(np.eye(40) * 4 + rng.normal(0, 0.1, (40, 40)), jnp.float32)
    config = configs.tiny()
    run = jax.jit(lambda threshold: head(src, tgt, scores, jnp.float32(1.0), config, True, threshold).weights)
    weights = {}
    for threshold in (0.3, 0.9):
        weights[threshold] = np.asarray(run(jnp.float32(threshold)))
        own = head(src, tgt, scores, jnp.float32(1.0), config.replace(gmcce_threshold=threshold), True)
        np.testing.assert_array_equal(weights[threshold], np.asarray(own.weights))
    assert weights[0.3].sum() > weights[0.9].sum()
