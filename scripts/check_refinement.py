"""Measures DIT's ICP refinement (:func:`dit_jax.icp.refine`) against its parts on validation pairs of
training shapes, per setting: what the shared-points switch (:data:`dit_jax.icp.SHARED_POINTS_GAP`) is based on.

    python scripts/check_refinement.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen \
        --out docs/refinement_check.md

Rows per setting: mean / median rotation error (degrees) and the share within 5 degrees of DIT alone (the
shipped weights as they ship), point-to-plane ICP at REFINE_DISTANCES, point-to-point at (0.1, 0.05, 0.025),
and ``refine`` (point-to-point where the clouds share their points) with each limit on how far it may move
the points (:data:`SHIFTS`; the shipped one is MAX_SHIFT); and the median gap after point-to-plane over the
target's spacing, which tells shared points from independent ones.
"""

import argparse
import datetime
import sys

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from dit_jax import icp, model, registration, training
from dit_jax.data.pairs import SETTINGS
from dit_jax.plotting import rotation_angle_deg

SHIFTS = (None, 0.3, 0.5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true")
    parser.add_argument("--pairs", type=int, default=16)
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--out", default=None, help="also write the table here (markdown)")
    args = parser.parse_args()
    batches = training.validation_batches(args.data_dir, list(SETTINGS), count=args.pairs, unseen=args.unseen)
    registrar = registration.load(args.checkpoint)
    columns = ("DIT alone", "point-to-plane", "point-to-point x3") + tuple(
        f"refine, shift <= {v}" + (" (shipped)" if v == icp.MAX_SHIFT else "") for v in SHIFTS)
    lines = [f"DIT's ICP refinement on {args.pairs} validation pairs per setting (training shapes"
             + (", categories 0-19" if args.unseen else "") + f"), {datetime.date.today().isoformat()}: "
             f"`python {' '.join(sys.argv)}`", "",
             "mean / median rotation error (deg) / share within 5 deg; gap: median distance to the nearest "
             "target point after point-to-plane over the target's point spacing", "",
             "| setting | " + " | ".join(columns) + " | gap |", "|---|" + "---|" * (len(columns) + 1)]
    for setting, b in batches.items():
        rotations, translations, _ = model.register(registrar.params, jnp.asarray(b["src"]), jnp.asarray(b["tgt"]),
                                                    registrar.config)
        errors = {c: [] for c in columns}
        gaps = []
        for i in range(len(b["src"])):
            src, tgt = b["src"][i].astype(np.float64), b["tgt"][i].astype(np.float64)
            r0, t0 = np.asarray(rotations[i], np.float64), np.asarray(translations[i], np.float64)
            plane = icp.icp(src, tgt, r0, t0, distances=icp.REFINE_DISTANCES, method="point_to_plane")
            point = icp.icp(src, tgt, r0, t0, distances=(0.1, 0.05, 0.025))
            refined = [icp.refine(src, tgt, r0, t0, max_shift=v).rotation for v in SHIFTS]
            for column, rotation in zip(columns, (r0, plane.rotation, point.rotation, *refined)):
                errors[column].append(rotation_angle_deg(rotation.T @ b["R"][i]))
            tree = cKDTree(tgt)
            gaps.append(np.median(tree.query(src @ plane.rotation.T + plane.translation)[0]) / icp.spacing(tgt, tree))
        cells = " | ".join(f"{np.mean(v):.2f} / {np.median(v):.3f} / {np.mean(np.array(v) <= 5):.2f}"
                           for v in errors.values())
        lines.append(f"| {setting} | {cells} | {np.median(gaps):.2f} |")
        print(lines[-1], flush=True)
    table = "\n".join(lines) + "\n"
    if args.out:
        with open(args.out, "w") as f:
            f.write(table)


if __name__ == "__main__":
    main()
