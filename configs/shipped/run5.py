"""Run 5 of 7 of the shipped weights (dit_jax/network/weights/dit-cpu-modelnet40), from run 4's weights: 1800 steps, the
best validation checkpoint kept (step 1800).

As run then, in the command-line syntax of then (``dit_jax.release.ship_weights`` recorded it):

    python train.py --preset cpu --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --settings clean \
        low_noise_partial high_noise_partial independent_clean independent_clean independent_high_noise_partial \
        scan_low_noise scan_high_noise scan_high_noise --init-from dit_jax/network/weights/dit-cpu-modelnet40 --set \
        max_steps=1800 --set match_radius=0.07 --set correspondence_weight=1.0 --set lr=3e-4 --set \
        'lr_drops=(0.85,)' --set val_pairs=16 --set eval_every=100 --set ckpt_every=50 --no-progress --workdir \
        runs/x28/stage6

Re-run today, after run 4: ``python train.py --config configs/shipped/run5.py --workdir
runs/shipped/run5`` (it starts from ``runs/shipped/run4/model``, which run 4's re-run writes).
"""

import dataclasses
import os

from dit_jax.training import load_config


def get_config():
    before = load_config(os.path.join(os.path.dirname(__file__), "run4.py"))  # run 4's recipe, changed:
    return dataclasses.replace(before, init_from="runs/shipped/run4/model", max_steps=1800).to_config_dict()
