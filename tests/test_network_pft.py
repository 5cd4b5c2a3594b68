import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.network import configs, pft


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


def test_deepen_adds_layers_that_change_nothing_until_trained():
    """A 1-block PFT grown to 3 blocks computes the same outputs; its new layers are fresh but for the zeroed
    residual outputs (so training can use them), and a narrower network is refused."""
    import pytest

    shallow, deep = configs.tiny(), configs.tiny().replace(n_blocks=3)
    f_x = jax.random.normal(jax.random.key(0), (20, shallow.emb_dims))
    f_y = jax.random.normal(jax.random.key(1), (15, shallow.emb_dims))
    small = pft.PFT(shallow).init(jax.random.key(2), f_x, f_y)["params"]
    fresh = pft.PFT(deep).init(jax.random.key(3), f_x, f_y)["params"]
    grown = pft.deepen(small, fresh)
    for before, after in zip(
        pft.PFT(shallow).apply({"params": small}, f_x, f_y), pft.PFT(deep).apply({"params": grown}, f_x, f_y)
    ):
        np.testing.assert_allclose(np.asarray(after), np.asarray(before), atol=1e-6)
    new = grown["decoder"]["layers_2"]
    assert not np.any(np.asarray(new["src_attn"]["o"]["kernel"]))
    assert not np.any(np.asarray(new["feed_forward"]["w_2"]["bias"]))
    np.testing.assert_array_equal(
        np.asarray(new["src_attn"]["q"]["kernel"]), np.asarray(fresh["decoder"]["layers_2"]["src_attn"]["q"]["kernel"])
    )
    # Training moves the new layers off identity: the deeper network then differs.
    moved = jax.tree.map(lambda a: a + 0.1, grown)
    assert not np.allclose(
        np.asarray(pft.PFT(deep).apply({"params": moved}, f_x, f_y)[0]),
        np.asarray(pft.PFT(shallow).apply({"params": small}, f_x, f_y)[0]),
    )
    wider = configs.tiny().replace(emb_dims=64, token_dim=8, n_blocks=2)
    g_x = jax.random.normal(jax.random.key(0), (20, 64))
    with pytest.raises(ValueError, match="shape"):
        pft.deepen(small, pft.PFT(wider).init(jax.random.key(3), g_x, g_x)["params"])
