import pytest

from dit_jax.network import configs


def test_paper_config_matches_the_paper():
    c = configs.paper()
    assert (c.emb_dims, c.token_dim, c.n_blocks, c.ff_dims, c.n_heads, c.k, c.n_iters) == (512, 64, 12, 1024, 4, 20, 3)
    assert (c.gmcce_k, c.gmcce_sharpness) == (10, 30.0)
    assert [configs.paper(s).gmcce_threshold for s in ("clean", "low_noise_partial", "high_noise_partial")] == [
        0.99,
        0.9,
        0.6,
    ]


def test_configs_are_hashable_values():
    assert configs.cpu() == configs.cpu() and hash(configs.cpu()) == hash(configs.cpu())
    assert configs.cpu().replace(n_iters=2).n_iters == 2


def test_invalid_configs_say_what_is_wrong():
    with pytest.raises(ValueError, match=r"emb_dims \(100\) must be 8 \* token_dim \(16\)"):
        configs.DITConfig(emb_dims=100, token_dim=16)
    with pytest.raises(ValueError, match="unknown config 'huge'"):
        configs.get("huge")
    with pytest.raises(ValueError, match="unknown DITConfig fields: bogus"):
        configs.DITConfig.from_dict({"bogus": 1})


def test_from_authors_reads_their_argument_names():
    c = configs.from_authors(
        "{'n_emb_dims': 128, 'token_dim': 16, 'n_blocks': 2, 'n_ff_dims': 256, 'n_heads': 4, 'k': 20, 'n_points': 256}"
    )
    assert (c.emb_dims, c.token_dim, c.n_blocks, c.ff_dims) == (128, 16, 2, 256)
