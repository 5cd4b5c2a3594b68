"""Rebuilds tests/data/tiny_state_dict.{pth,npz}: the tiny config's init(key 0) params under the authors' names,
saved by real PyTorch (2.13), and the same arrays as .npz, so that the torch-free reader is tested against PyTorch's own file format.

    python tests/data/make_tiny_pth.py    (needs torch)
"""

import collections
import pathlib

import jax
import numpy as np
import torch

from dit_jax.network import configs, convert, model

config = configs.tiny()
state = convert.to_torch_state_dict(model.init(jax.random.key(0), config), config)
tensors = collections.OrderedDict((k, torch.from_numpy(v.copy())) for k, v in state.items())
# The authors' unused tensors are in their files too; the reader must skip them.
tensors["head.reflect"] = torch.eye(3)
tensors["emb_nn.project.weight"] = torch.zeros(config.emb_dims, config.token_dim * 4)
# Checkpoints saved from nn.DataParallel prefix every name with "module.".
wrapped = {"epoch": 7, "state_dict": collections.OrderedDict(("module." + k, v) for k, v in tensors.items())}
torch.save(wrapped, pathlib.Path(__file__).with_name("tiny_state_dict.pth"))
np.savez(pathlib.Path(__file__).with_name("tiny_state_dict.npz"), **{k: v.numpy() for k, v in tensors.items()})
