import jax
import jax.numpy as jnp
import numpy as np

from dit_jax import configs, pft


def test_annotated_layer_norm_uses_unbiased_std_plus_eps():
    x = jnp.array([[1.0, 2.0, 3.0, 6.0]])
    module = pft.AnnotatedLayerNorm()
    out = module.apply(module.init(jax.random.key(0), x), x)
    expected = (x - 3.0) / (np.std(np.asarray(x), ddof=1) + 1e-6)
    np.testing.assert_allclose(np.asarray(out), np.asarray(expected), rtol=1e-6)


def test_pft_is_one_function_applied_in_both_directions():
    config = configs.tiny()
    f_x = jax.random.normal(jax.random.key(0), (20, config.emb_dims))
    f_y = jax.random.normal(jax.random.key(1), (15, config.emb_dims))
    module = pft.PFT(config)
    variables = module.init(jax.random.key(2), f_x, f_y)
    src_p, tgt_p = module.apply(variables, f_x, f_y)
    assert src_p.shape == f_x.shape and tgt_p.shape == f_y.shape
    swapped_src, swapped_tgt = module.apply(variables, f_y, f_x)
    np.testing.assert_allclose(np.asarray(swapped_src), np.asarray(tgt_p), atol=1e-6)
    np.testing.assert_allclose(np.asarray(swapped_tgt), np.asarray(src_p), atol=1e-6)


def test_dropout_only_in_training():
    config = configs.tiny()
    f_x = jax.random.normal(jax.random.key(0), (20, config.emb_dims))
    module = pft.PFT(config)
    variables = module.init(jax.random.key(2), f_x, f_x)
    a = module.apply(variables, f_x, f_x)[0]
    b = module.apply(variables, f_x, f_x)[0]
    c = module.apply(variables, f_x, f_x, deterministic=False, rngs={"dropout": jax.random.key(3)})[0]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(a), np.asarray(c))


def test_squeeze_excitation_rescales_channels_only():
    f = jax.random.normal(jax.random.key(0), (10, 32))
    module = pft.SqueezeExcitation(32)
    out = module.apply(module.init(jax.random.key(1), f), f)
    gate = np.asarray(out / f)
    np.testing.assert_allclose(gate, np.broadcast_to(gate[0], gate.shape), rtol=1e-5)
    assert ((gate > 0) & (gate < 1)).all()
