"""Writes examples/chair_src.ply and examples/chair_tgt.pcd, the pair the README registers.

The oak chair of the embedded set (BlendSwap-CC-0/oakChair by Doug C, CC0), scaled to about a metre and set
in a room frame; the target is the same chair turned by 30 degrees about the vertical, tilted 5 degrees,
moved 0.35 m, with 1 mm of Gaussian noise and its points shuffled. The true motion is printed.

    python scripts/make_example_pair.py
"""

import os

import numpy as np

from dit_jax import io
from dit_jax.data.pairs import euler_zyx_to_matrix

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "examples")


def main() -> None:
    data = np.load(os.path.join(HERE, "..", "dit_jax", "data", "embedded", "sh3d_furniture_1024.npz"))
    index = int(np.flatnonzero(data["id"] == "BlendSwap-CC-0/oakChair")[0])
    shape = data["points"][index].astype(np.float64) / 32767.0  # the unit sphere, as stored
    src = shape * 0.5 + np.array([2.0, 1.5, 0.5])  # metres, in a room
    rotation = euler_zyx_to_matrix([30.0, 5.0, 0.0])
    translation = np.array([0.25, -0.2, 0.1]) + np.array([2.0, 1.5, 0.5]) - rotation @ np.array([2.0, 1.5, 0.5])
    rng = np.random.default_rng(0)
    tgt = src @ rotation.T + translation + rng.normal(scale=0.001, size=src.shape)
    tgt = tgt[rng.permutation(len(tgt))]
    io.write(os.path.join(OUT, "chair_src.ply"), src.astype(np.float32))
    io.write(os.path.join(OUT, "chair_tgt.pcd"), tgt.astype(np.float32), binary=False)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    with np.printoptions(precision=6, suppress=True):
        print(matrix)


if __name__ == "__main__":
    main()
