"""The smallest network, for tests: a few steps on 64-point clouds, a mix of a clean and a partial setting
(one cloud size for both, so one compiled train step)."""

from dit_jax.network import configs
from dit_jax.training import TrainConfig


def get_config():
    return TrainConfig(
        model=configs.tiny("clean"),
        settings=("clean", "low_noise_partial"),
        n_points=64,
        batch_size=4,
        epochs=1,
        lr=1e-3,
        val_pairs=8,
        eval_every=10,
        ckpt_every=5,
        log_every=1,
        train_iters=1,
    ).to_config_dict()
