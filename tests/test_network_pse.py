import jax
import jax.numpy as jnp
import numpy as np

from dit_jax.geometry import rigid
from dit_jax.network import configs, pse


def test_lfi_concatenates_neighbour_features_nearest_first():
    features = jnp.arange(10.0).reshape(5, 2)
    idx = jnp.array([[0, 3, 1]] * 5)
    out = pse.local_feature_integration(features, idx)
    assert out.shape == (5, 6)
    np.testing.assert_array_equal(np.asarray(out[0]), [0, 1, 6, 7, 2, 3])


def test_pse_widths_follow_the_config():
    config = configs.tiny()
    points = jax.random.normal(jax.random.key(0), (30, 3))
    idx = rigid.knn(points, config.k)
    module = pse.PSE(config)
    variables = module.init(jax.random.key(1), points, idx)
    out = module.apply(variables, points, idx)
    assert out.shape == (30, config.emb_dims)
    # Layer 1 reads k xyz triples, the others k tokens.
    assert variables["params"]["attention1"]["norm1"]["scale"].shape == (3 * config.k,)
    assert variables["params"]["attention2"]["norm1"]["scale"].shape == (config.token_dim * config.k,)
    # LayerNorm at the end: every point's feature has zero mean over channels.
    np.testing.assert_allclose(np.asarray(out.mean(-1)), 0.0, atol=1e-5)
