"""What ``python train.py`` runs: the ``cpu`` network on the embedded set, 256 points, 4 epochs; a short run
that ends within minutes on two CPU cores."""

from dit_jax.network import configs
from dit_jax.training import TrainConfig


def get_config():
    return TrainConfig(
        model=configs.cpu("clean"),
        n_points=256,
        batch_size=8,
        epochs=4,
        lr=1e-3,
        val_pairs=32,
        eval_every=50,
        ckpt_every=50,
        log_every=5,
        train_precision="auto",
    ).to_config_dict()
