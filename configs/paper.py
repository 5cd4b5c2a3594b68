"""The authors' recipe (docs/network.md, section 11): the paper's network, 1000 points, batch 2, Adam 3e-5,
weight decay 1e-4, the learning rate dropped at 30, 60 and 80 % of the run."""

from dit_jax.network import configs
from dit_jax.training import TrainConfig


def get_config():
    return TrainConfig(
        model=configs.paper("clean"),
        n_points=1000,
        batch_size=2,
        epochs=100,
        lr=3e-5,
        weight_decay=1e-4,
        eval_every=2000,
        ckpt_every=1000,
        train_precision="auto",
    ).to_config_dict()
