"""Writes examples/chair_src.ply and examples/chair_tgt.pcd, the pair the README registers.

Two scan-like views of one object, as a user's scanner gives them: the oak chair of the embedded set
(BlendSwap-CC-0/oakChair by Doug C, CC0), scaled to about a metre and set in a room frame, seen from two
viewpoints 40 degrees apart (hidden-point removal, :func:`dit_jax.data.views.visible_points`). Points both
views see go to one of them at random, so the two clouds share no point; each gets 1 mm of Gaussian noise.
The target is then turned by 30 degrees about the vertical, tilted 5 degrees, moved 0.35 m and shuffled.
The true motion is printed and written to examples/chair_truth.txt.

    python tools/make_example_pair.py [--out DIR]
"""

import argparse
import os

import numpy as np

from dit_jax import io
from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.data.views import visible_points

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "examples")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=OUT, help="the folder to write the three files to (default: examples/)")
    out = parser.parse_args(argv).out
    os.makedirs(out, exist_ok=True)
    data = np.load(os.path.join(HERE, "..", "dit_jax", "data", "embedded", "sh3d_furniture_1024.npz"))
    index = int(np.flatnonzero(data["id"] == "BlendSwap-CC-0/oakChair")[0])
    shape = data["points"][index].astype(np.float64) / 32767.0  # the unit sphere, as stored
    rng = np.random.default_rng(0)
    views = []
    for azimuth in (-20.0, 20.0):  # degrees about the vertical (z), both from the front and a little above
        a = np.radians(azimuth)
        views.append(visible_points(shape, 2.0 * np.array([np.sin(a), -np.cos(a), 0.4])))
    coin = rng.random(len(shape)) < 0.5
    src_rows = np.flatnonzero(views[0] & (~views[1] | coin))
    tgt_rows = np.flatnonzero(views[1] & (~views[0] | ~coin))
    room = np.array([2.0, 1.5, 0.5])
    src = shape[src_rows] * 0.5 + room + rng.normal(scale=0.001, size=(len(src_rows), 3))  # metres
    tgt_before = shape[tgt_rows] * 0.5 + room + rng.normal(scale=0.001, size=(len(tgt_rows), 3))
    rotation = euler_zyx_to_matrix([30.0, 5.0, 0.0])
    translation = np.array([0.25, -0.2, 0.1]) + room - rotation @ room
    tgt = (tgt_before @ rotation.T + translation)[rng.permutation(len(tgt_rows))]
    io.write(os.path.join(out, "chair_src.ply"), src.astype(np.float32))
    io.write(os.path.join(out, "chair_tgt.pcd"), tgt.astype(np.float32), binary=False)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    np.savetxt(
        os.path.join(out, "chair_truth.txt"),
        matrix,
        fmt="%.9f",
        header="true 4x4 motion of chair_src.ply onto chair_tgt.pcd (tgt = R src + t)",
    )
    print(f"source {len(src)} points, target {len(tgt)} points, none shared")
    with np.printoptions(precision=6, suppress=True):
        print(matrix)


if __name__ == "__main__":
    main()
