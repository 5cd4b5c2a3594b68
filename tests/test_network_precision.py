"""DITConfig.precision reaches every matrix product of registration and of the train step.

The jaxprs are inspected rather than the numbers, because on a CPU every precision computes float32 and
the numbers would not tell. Each test traces under a global ``jax.default_matmul_precision`` other than
the configured one: a product without its own precision would take the global one and show up.
"""

import dataclasses
import pathlib

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from dit_jax import training
from dit_jax.network import configs, layers, model

HIGHEST = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
EXPECTED = {
    "highest": HIGHEST,
    "tf32": (jax.lax.Precision.HIGH, jax.lax.Precision.HIGH),
    "bfloat16": (jax.lax.Precision.DEFAULT, jax.lax.Precision.DEFAULT),
}
# Another global default for each setting, so that a product that ignores the config is seen.
OTHER_GLOBAL = {"highest": "bfloat16", "tf32": "float32", "bfloat16": "float32"}


def _products(jaxpr):
    """Every dot_general and convolution of a jaxpr, sub-jaxprs (scan, cond, remat, custom_vjp, pjit) included."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("dot_general", "conv_general_dilated"):
            found.append(eqn)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    found += _products(sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    found += _products(sub)
    return found


def _is_geometry(eqn) -> bool:
    """Products of coordinates or 3 x 3 rotations (Procrustes, transforms, soft targets, losses): they stay at
    the highest precision whatever the setting. Every one has a coordinate axis (size 3) last."""
    shapes = [v.aval.shape for v in (*eqn.invars, *eqn.outvars)]
    return any(len(s) >= 1 and s[-1] == 3 for s in shapes)


def _has_vector_operand(eqn) -> bool:
    """Products of a vector (the squeeze-and-excitation gate, the temperature net): "bfloat16" leaves them
    float32 at the highest precision (dit_jax.network.layers._operands)."""
    return any(len(v.aval.shape) == 1 for v in eqn.invars)


def _check(jaxpr, precision: str) -> int:
    products = _products(jaxpr)
    assert products, "no matrix product found: the walk over the jaxpr is broken"
    network = 0
    for eqn in products:
        got = eqn.params["precision"]
        if _is_geometry(eqn):
            assert got in (HIGHEST, EXPECTED[precision]), f"{eqn} has precision {got}"
        elif precision == "bfloat16" and _has_vector_operand(eqn):
            network += 1
            assert got == HIGHEST and all(v.aval.dtype == jnp.float32 for v in eqn.invars), f"{eqn}: {got}"
        else:
            network += 1
            assert got == EXPECTED[precision], f"{eqn} has precision {got}, expected {EXPECTED[precision]}"
            if precision == "bfloat16":  # rounded operands (the backward pass multiplies a float32 cotangent)
                assert any(v.aval.dtype == jnp.bfloat16 for v in eqn.invars), f"{eqn} multiplies float32"
    return network


@pytest.mark.parametrize("precision", configs.PRECISIONS)
def test_every_product_of_registration_has_the_configured_precision(precision):
    config = configs.tiny().replace(precision=precision, n_iters=2)
    params = model.init(jax.random.PRNGKey(0), config)
    src = jax.random.normal(jax.random.PRNGKey(1), (2, 24, 3))
    with jax.default_matmul_precision(OTHER_GLOBAL[precision]):
        jaxpr = jax.make_jaxpr(lambda p, a, b: model.register(p, a, b, config))(params, src, src[:, ::-1])
    # PSE (8 layers x 6), PFT, SE, temperature net and similarity: dozens of network products.
    assert _check(jaxpr.jaxpr, precision) > 50


@pytest.mark.parametrize("precision", configs.PRECISIONS)
def test_every_product_of_the_train_step_has_the_configured_precision(precision):
    recipe = training.load_config(pathlib.Path(__file__).resolve().parents[1] / "configs" / "tiny.py")
    config = dataclasses.replace(recipe, n_points=24, model=recipe.model.replace(precision=precision))
    optimizer = training.make_optimizer(config, 10)
    mesh = training.make_mesh(jax.devices()[:1])
    state = training.init_state(config, optimizer)
    rotation = jnp.broadcast_to(jnp.eye(3), (4, 3, 3))
    batch = {"src": jnp.ones((4, 24, 3)), "tgt": jnp.ones((4, 24, 3)), "R": rotation, "t": jnp.zeros((4, 3))}
    step = training.make_train_step(config, optimizer, mesh)
    with jax.default_matmul_precision(OTHER_GLOBAL[precision]):
        jaxpr = jax.make_jaxpr(step)(state, batch)
    # The forward products and both transposes of each in the backward pass.
    assert _check(jaxpr.jaxpr, precision) > 100


def test_dot_precision_names_and_bad_name():
    assert layers.dot_precision("highest") == jax.lax.Precision.HIGHEST
    with pytest.raises(ValueError, match="precision"):
        layers.dot_precision("fp8")
    with pytest.raises(ValueError, match="precision must be one of"):
        configs.tiny().replace(precision="float32")


def test_default_is_highest_and_old_configs_load_with_it():
    assert configs.paper().precision == "highest"
    values = configs.cpu().to_dict()
    del values["precision"]  # a checkpoint written before the setting existed
    assert configs.DITConfig.from_dict(values).precision == "highest"


def test_precisions_agree_on_cpu_within_bfloat16_rounding():
    """On a CPU "tf32" computes float32 (the same numbers as "highest"); "bfloat16" rounds the operands."""
    src = jax.random.normal(jax.random.PRNGKey(2), (1, 32, 3))
    tgt = src[:, ::-1] + 0.1
    results = {}
    for precision in configs.PRECISIONS:
        config = configs.tiny().replace(precision=precision, n_iters=1)
        params = model.init(jax.random.PRNGKey(0), config)
        results[precision] = np.asarray(model.register(params, src, tgt, config)[0])
    np.testing.assert_allclose(results["tf32"], results["highest"], atol=1e-6)
    np.testing.assert_allclose(results["bfloat16"], results["highest"], atol=0.1)


def test_the_registration_api_takes_a_precision():
    from dit_jax.pipeline import registration

    assert registration.load().config.precision == "highest"
    assert registration.load(precision="tf32").config.precision == "tf32"
    with pytest.raises(ValueError, match="precision must be one of"):
        registration.load(precision="half")
