"""A CPU-sized network and point count that learns in hours on two cores."""

from dit_jax.network import configs
from dit_jax.training import TrainConfig


def get_config():
    return TrainConfig(
        model=configs.cpu("clean"), n_points=512, batch_size=8, epochs=100, lr=1e-3, train_precision="auto"
    ).to_config_dict()
