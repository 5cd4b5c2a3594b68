"""Measures DIT+ICP with and without ``best_direction`` (keep whichever of the two refined registrations,
source onto target or the inverse of target onto source, fits the clouds better; see
:class:`dit_jax.registration.Registrar`) on validation pairs of training shapes, per setting, the authors' and
the peers' variants. The same library calls evaluate.py makes (:func:`dit_jax.evaluation.choose_direction`).

    python scripts/check_best_direction.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen --pairs 24

Cells: mean rotation error (degrees) / share within 5 degrees / share within 1 degree.
"""

import argparse
import datetime
import sys

import numpy as np

from dit_jax import checkpoint, evaluation, registration, training
from dit_jax.data import pairs as pairs_lib, shapes as shapes_lib
from dit_jax.data.pairs import SETTINGS
from dit_jax.geometry import rotation_angle_deg

CASES = [("authors", s) for s in SETTINGS] + [("peers", "low_noise_partial"), ("peers", "high_noise_partial")]


def _cell(errors: np.ndarray) -> str:
    return f"{errors.mean():.2f} / {np.mean(errors <= 5):.2f} / {np.mean(errors <= 1):.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=24)
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--out", default=None, help="also write the table here (markdown)")
    args = parser.parse_args()
    path = args.checkpoint or registration.shipped_weights()
    params, config = checkpoint.restore(path)
    n_points = checkpoint.read_extra(path).get("inference_points") or 1000
    shapes = shapes_lib.load_shapes(args.data_dir, "train",
                                    n_points=pairs_lib.shape_points(args.data_dir, n_points, list(SETTINGS)))
    _, val_shapes = training.split_validation(shapes, training.TrainConfig().val_fraction)
    lines = [f"DIT+ICP from one direction and the better fitting of both, {args.pairs} validation pairs per "
             f"setting (training shapes{', categories 0-19' if args.unseen else ''}), "
             f"{datetime.date.today().isoformat()}: `python {' '.join(sys.argv)}`", "",
             "mean rotation error (deg) / share within 5 deg / share within 1 deg", "",
             "| setting | DIT+ICP (source onto target) | DIT+ICP, best direction | pairs where it keeps the backward one |",
             "|---|---|---|---|"]
    for variant, setting in CASES:
        ds = pairs_lib.PairDataset(val_shapes, pairs_lib.PairConfig(setting=setting, variant=variant,
                                                                     n_points=n_points))
        if args.unseen:
            ds.rows = ds.rows[val_shapes.labels[ds.rows] < 20]
        indices = np.linspace(0, len(ds) - 1, args.pairs).astype(int)
        dit = evaluation.predict_dit(params, config, ds, indices)
        refined = evaluation.refine_dit(dit, ds, indices, truth_fit=False)
        backward = evaluation.backward_agreement(params, config, ds, indices, dit, refined)
        chosen = evaluation.choose_direction(refined, backward[evaluation.METHOD_DIT_ICP], ds, indices)
        truth = ds.batch(indices)["R"]
        errors = [np.array([rotation_angle_deg(r.T @ t) for r, t in zip(p["R"], truth)]) for p in (refined, chosen)]
        name = setting if variant == "authors" else f"{setting} (peers)"
        lines.append(f"| {name} | {_cell(errors[0])} | {_cell(errors[1])} | {int(chosen['backward'].sum())} |")
        print(lines[-1], flush=True)
    table = "\n".join(lines) + "\n"
    if args.out:
        with open(args.out, "w") as f:
            f.write(table)


if __name__ == "__main__":
    main()
