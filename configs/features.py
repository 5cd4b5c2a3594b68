"""The learned descriptor of room scans (dit_jax.features.network), trained on the shared 3DMatch scenes:

python train.py --config configs/features.py                          # every scene: the shipped weights
python train.py --config configs/features.py --config.holdout=hotel3  # one scene left out, validated on
"""

import os

from dit_jax.training.descriptor import DescriptorTrainConfig

ROOMS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "..", "shared", "data", "3dmatch")


def get_config():
    return DescriptorTrainConfig(data_dir=os.path.normpath(ROOMS)).to_config_dict()
