"""Run 7 of 7 of the shipped weights (dit_jax/network/weights/dit-cpu-modelnet40), from run 6's weights, on one lent
NVIDIA H200: 4500 steps in one 500-second lease, the last checkpoint kept (step 4500, validated once, at the
end). Fresh pairs (seed 7, never drawn by an earlier run) of run 6's mix, with every cloud of more than 384
points thinned to 384 by a sampler drawn per cloud (uniform, a density gradient, farthest-point), so that no
single sampling pattern is learned; validation thins the held-out shapes' pairs the same way. On ModelNet40's
1024-point shapes the scan-like views hold 205 points, so the mix keeps two sizes, 384 and 205 (two compiled
train steps).

As run then, in the syntax of then (``dit_jax.release.ship_weights`` recorded it; the training shapes packed
here with ``python -m dit_jax.release.device_stage pack``, docs/training.md; the tool is now
``python tools/device_stage.py``):

    python -m dit_jax.release.device_stage run --packed runs/device_data/mn40_train.npz --out $OUT \
        --seconds 530 --steps 4500 --validations 1 --ckpt-every 250 --run stage7 -- \
        --config configs/shipped/run7.py --no-progress

Re-run today (on 2 CPU cores too, in hours), after run 6: ``python train.py --config configs/shipped/run7.py --workdir
runs/shipped/run7`` (it starts from ``runs/shipped/run6/model``, which run 6's re-run writes).
"""

import dataclasses
import os

from dit_jax.training import load_config


def get_config():
    before = load_config(os.path.join(os.path.dirname(__file__), "run6.py"))  # run 6's recipe, changed:
    return dataclasses.replace(
        before,
        init_from="runs/shipped/run6/model",
        seed=7,
        mix_one_size=False,
        mix_points=384,
        mix_sampling="varied",
        max_steps=4500,
        lr_drops=(0.9,),
        val_pairs=16,
        validate_at_start=False,
        eval_every=4500,
        ckpt_every=250,
        keep=1,
    ).to_config_dict()
