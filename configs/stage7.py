"""The next stage of the shipped weights (issue 53): from them, on pairs no earlier stage drew (seed 7), the
shipped runs' mix of settings with every cloud of more than 384 points thinned to 384 by a sampler drawn per
cloud (uniform, a density gradient, farthest-point), so that no single sampling pattern is learned;
validation thins the held-out shapes' pairs the same way. On ModelNet40's 1024-point shapes the scan-like
views hold 205 points: one size for the whole mix would thin every setting to 205 (the shipped weights
register at 1000), so this stage keeps two sizes, 384 and 205 (two compiled train steps). Long: run it in the
background and resume it across days.

    python train.py --config configs/stage7.py --workdir runs/stage7 --no-progress
    python train.py --workdir runs/stage7 --resume --no-progress
"""

import dataclasses
import os

from dit_jax.training import load_config


def get_config():
    shipped = load_config(os.path.join(os.path.dirname(__file__), "shipped", "run6.py"))
    return dataclasses.replace(shipped, init_from="dit_jax/weights/dit-cpu-modelnet40", seed=7,
                               mix_one_size=False, mix_points=384, mix_sampling="varied",
                               max_steps=20000, lr_drops=(0.9,), val_pairs=16, eval_every=250,
                               ckpt_every=50).to_config_dict()
