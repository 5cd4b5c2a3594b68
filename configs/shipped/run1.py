"""Run 1 of 7 of the shipped weights (dit_jax/network/weights/dit-cpu-modelnet40), from the weights shipped before it (a
clean run's best, 200 steps; their record is not kept): 600 steps, the best validation checkpoint kept (step
600).

As run then, in the command-line syntax of then (``dit_jax.release.ship_weights`` recorded it):

    python train.py --preset cpu --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --setting clean --unseen \
        --set max_steps=1000 --set 'lr_drops=(0.6,0.85)' --workdir runs/mn40-clean  (stopped after step 240; its \
        best, step 200, exported to runs/mn40-clean/model); then python train.py --preset cpu --data-dir \
        ../shared/data/modelnet40_ply_hdf5_1024 --setting low_noise_partial --unseen --init-from \
        runs/mn40-clean/model --set max_steps=600 --set 'lr_drops=(0.5,0.8)' --set eval_every=150 --workdir \
        runs/mn40-lownoise

Re-run today: ``python train.py --config configs/shipped/run1.py --workdir runs/shipped/run1``. Run 1
started from run 0's weights, which were not kept, so this file starts from the shipped weights: a
re-run of the chain from it trains those further and does not rebuild them.
"""

from dit_jax.network import configs
from dit_jax.training import TrainConfig


def get_config():
    return TrainConfig(
        model=configs.cpu("low_noise_partial"),
        setting="low_noise_partial",
        data_dir="../shared/data/modelnet40_ply_hdf5_1024",
        unseen=True,
        n_points=512,
        max_steps=600,
        lr_drops=(0.5, 0.8),
        eval_every=150,
        init_from="dit_jax/network/weights/dit-cpu-modelnet40",
    ).to_config_dict()
