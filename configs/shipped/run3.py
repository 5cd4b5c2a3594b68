"""Run 3 of 7 of the shipped weights (dit_jax/network/weights/dit-cpu-modelnet40), from run 2's weights: 1000 steps, the
best validation checkpoint kept (step 1000).

As run then, in the command-line syntax of then (``dit_jax.release.ship_weights`` recorded it):

    python train.py --preset cpu --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --settings clean \
        low_noise_partial high_noise_partial independent_clean independent_clean independent_high_noise_partial \
        scan_low_noise scan_high_noise scan_high_noise --init-from dit_jax/network/weights/dit-cpu-modelnet40 --set \
        max_steps=1000 --set match_radius=0.07 --set correspondence_weight=1.0 --set lr=3e-4 --set \
        'lr_drops=(0.8,)' --set val_pairs=16 --set eval_every=100 --set ckpt_every=50 --no-progress --workdir \
        runs/x25/mix_corr

Re-run today, after run 2: ``python train.py --config configs/shipped/run3.py --workdir
runs/shipped/run3`` (it starts from ``runs/shipped/run2/model``, which run 2's re-run writes).
"""

import dataclasses
import os

from dit_jax.training import load_config


def get_config():
    before = load_config(os.path.join(os.path.dirname(__file__), "run2.py"))  # run 2's recipe, changed:
    return dataclasses.replace(
        before,
        init_from="runs/shipped/run2/model",
        lr=0.0003,
        lr_drops=(0.8,),
        val_pairs=16,
        eval_every=100,
        correspondence_weight=1.0,
    ).to_config_dict()
