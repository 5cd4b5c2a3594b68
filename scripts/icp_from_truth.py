"""DIT's ICP refinement (:func:`dit_jax.icp.refine`, as ``register(refine="icp")`` runs it) started at the exact
truth, on ModelNet40 unseen test pairs of every setting. The refinement only leaves its start for a motion
that fits the clouds better (:func:`dit_jax.icp.trimmed_fit`), so every pair that ends more than 1 degree
off here is one whose points prefer a pose more than 1 degree from the truth: what "ends within 1 degree"
can ask of DIT + ICP on that setting.

    python scripts/icp_from_truth.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --pairs 100

Prints a markdown table: median / mean / worst rotation error after refinement and how many pairs end more
than 1 degree off. Point count: the shipped weights' (as evaluate.py uses).
"""

import argparse
import datetime

import numpy as np

from dit_jax import icp, registration
from dit_jax.data import pairs as pairs_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.plotting import rotation_angle_deg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", required=True, help="ModelNet40 in the h5 layout")
    parser.add_argument("--pairs", type=int, default=100, help="the first pairs of each setting")
    args = parser.parse_args()
    n_points = registration.load().n_points
    settings = list(pairs_lib.SETTINGS)
    shapes = shapes_lib.load_shapes(args.data_dir, "test",
                                    n_points=pairs_lib.shape_points(args.data_dir, n_points, settings))
    print(f"{datetime.date.today().isoformat()}: `python scripts/icp_from_truth.py --data-dir {args.data_dir} "
          f"--pairs {args.pairs}` (unseen categories, {n_points} points)\n")
    print("| setting | median deg | mean deg | worst deg | more than 1 deg off |\n|---|---|---|---|---|")
    for setting in settings:
        dataset = pairs_lib.PairDataset(shapes, pairs_lib.PairConfig(setting=setting, unseen=True,
                                                                       n_points=n_points))
        errors = []
        for n in range(min(args.pairs, len(dataset))):
            pair = dataset[n]
            truth = pair["R"].astype(np.float64)
            refined = icp.refine(pair["src"], pair["tgt"], truth, pair["t"].astype(np.float64))
            errors.append(rotation_angle_deg(refined.rotation.T @ truth))
        errors = np.asarray(errors)
        print(f"| {setting} | {np.median(errors):.3f} | {errors.mean():.3f} | {errors.max():.2f} | "
              f"{int(np.sum(errors > 1.0))} of {len(errors)} |", flush=True)


if __name__ == "__main__":
    main()
