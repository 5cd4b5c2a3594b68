"""Stage 8 continued (configs/stage8.py): its recipe from its output (``runs/stage8/model``) for 2000 more steps
on fresh pairs (seed 10, never drawn by an earlier run), so that the two stages together spend about two thirds
of run 7's steps. Run in the background on 2 CPU cores, resuming across sessions:

    python train.py --config configs/stage9.py --workdir runs/stage9 --no-progress
    python train.py --config configs/stage9.py --workdir runs/stage9 --resume --no-progress

It ships only if it passes the shipping rule (``python -m dit_jax.release.shipping_rule``, docs/training.md).
"""

import dataclasses
import os

from dit_jax.training import load_config


def get_config():
    before = load_config(os.path.join(os.path.dirname(__file__), "stage8.py"))  # stage 8's recipe, changed:
    return dataclasses.replace(
        before,
        init_from="runs/stage8/model",
        seed=10,
        max_steps=2000,
        lr_drops=(0.8,),
        eval_every=2000,
    ).to_config_dict()
