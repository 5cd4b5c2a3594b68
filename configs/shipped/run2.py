"""Run 2 of 7 of the shipped weights (dit_jax/network/weights/dit-cpu-modelnet40), from run 1's weights: 1000 steps, the
best validation checkpoint kept (step 1000).

As run then, in the command-line syntax of then (``dit_jax.release.ship_weights`` recorded it):

    python train.py --preset cpu --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --settings clean \
        low_noise_partial high_noise_partial independent_clean independent_clean independent_high_noise_partial \
        scan_low_noise scan_high_noise scan_high_noise --init-from dit_jax/network/weights/dit-cpu-modelnet40 --set \
        max_steps=1000 --set lr=3e-4 --set 'lr_drops=(0.6,0.85)' --set match_radius=0.07 --set val_pairs=24 --set \
        eval_every=125 --set ckpt_every=50 --workdir runs/mix (stopped at step 500); then the same with --resume \
        --set lr=1e-3 --set 'lr_drops=(0.75,0.9)'

Re-run today, after run 1: ``python train.py --config configs/shipped/run2.py --workdir
runs/shipped/run2`` (it starts from ``runs/shipped/run1/model``, which run 1's re-run writes).
"""

import dataclasses
import os

from dit_jax.network import configs
from dit_jax.training import load_config


def get_config():
    before = load_config(os.path.join(os.path.dirname(__file__), "run1.py"))  # run 1's recipe, changed:
    return dataclasses.replace(
        before,
        init_from="runs/shipped/run1/model",
        model=configs.cpu("clean"),
        setting="clean",
        settings=(
            "clean",
            "low_noise_partial",
            "high_noise_partial",
            "independent_clean",
            "independent_clean",
            "independent_high_noise_partial",
            "scan_low_noise",
            "scan_high_noise",
            "scan_high_noise",
        ),
        mix_one_size=False,  # trained before the mix had one size
        max_steps=1000,
        lr_drops=(0.75, 0.9),
        val_pairs=24,
        eval_every=125,
        ckpt_every=50,
        match_radius=0.07,
    ).to_config_dict()
