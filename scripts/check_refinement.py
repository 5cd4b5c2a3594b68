"""Measures DIT's ICP refinement (:func:`dit_jax.icp.refine`) against each ICP run it chooses from, on
validation pairs of training shapes, per setting: what :data:`dit_jax.icp.REFINE_CANDIDATES` and the
selection by :func:`dit_jax.icp.trimmed_fit` are based on.

    python scripts/check_refinement.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen \
        --out docs/refinement_check.md

Cells: mean / median rotation error (degrees) / share within 5 degrees, for DIT alone (the shipped weights as
they ship), each candidate run alone (started at DIT's estimate), ``refine`` without its translation search
(:data:`dit_jax.icp.TRANSLATION_SEARCH`) and ``refine`` as it ships. The last column: of the
pairs DIT had within 10 degrees, how many ``refine`` ends within 1 degree, and of those it does not, how many
end where the clouds fit better than at the true pose (the data's doing, not the refinement's).
"""

import argparse
import datetime
import sys

import jax.numpy as jnp
import numpy as np

from dit_jax import icp, model, registration, training
from dit_jax.data.pairs import SETTINGS
from dit_jax.geometry import rotation_angle_deg


def _name(method: str, distances, trim) -> str:
    return f"{method.replace('_', '-')} {'/'.join(f'{d:g}' for d in distances)}" + (f" trim {trim:g}" if trim else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true")
    parser.add_argument("--pairs", type=int, default=48)
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--out", default=None, help="also write the table here (markdown)")
    args = parser.parse_args()
    batches = training.validation_batches(args.data_dir, list(SETTINGS), count=args.pairs, unseen=args.unseen)
    registrar = registration.load(args.checkpoint, verdict_rule="fitness")  # estimates only: one direction
    columns = (("DIT alone",) + tuple(_name(*c) for c in icp.REFINE_CANDIDATES)
               + ("refine, no translation search", "refine (shipped)"))
    lines = [f"DIT's ICP refinement on {args.pairs} validation pairs per setting (training shapes"
             + (", categories 0-19" if args.unseen else "") + f"), {datetime.date.today().isoformat()}: "
             f"`python {' '.join(sys.argv)}`", "",
             "mean / median rotation error (deg) / share within 5 deg; last column: of the pairs DIT had within "
             "10 deg, how many refine ends within 1 deg, and (in brackets) how many of the rest end where the "
             "clouds fit better than at the true pose", "",
             "| setting | " + " | ".join(columns) + " | DIT within 10 -> within 1 |", "|---|" + "---|" * (len(columns) + 1)]
    for setting, b in batches.items():
        rotations, translations, _ = model.register(registrar.params, jnp.asarray(b["src"]), jnp.asarray(b["tgt"]),
                                                    registrar.config)
        errors = {c: [] for c in columns}
        good = within = by_data = 0
        for i in range(len(b["src"])):
            src, tgt = b["src"][i].astype(np.float64), b["tgt"][i].astype(np.float64)
            r0, t0 = np.asarray(rotations[i], np.float64), np.asarray(translations[i], np.float64)
            runs = [icp.icp(src, tgt, r0, t0, distances=d, method=m, trim=trim)
                    for m, d, trim in icp.REFINE_CANDIDATES]
            plain = icp.refine(src, tgt, r0, t0, translation_search=None)
            refined = icp.refine(src, tgt, r0, t0)
            rotations_found = (r0, *(r.rotation for r in runs), plain.rotation, refined.rotation)
            for column, rotation in zip(columns, rotations_found):
                errors[column].append(rotation_angle_deg(rotation.T @ b["R"][i]))
            if errors["DIT alone"][-1] <= 10:
                good += 1
                if errors["refine (shipped)"][-1] <= 1:
                    within += 1
                elif icp.fits_better(src, tgt, (refined.rotation, refined.translation), (b["R"][i], b["t"][i])):
                    by_data += 1
        cells = " | ".join(f"{np.mean(v):.2f} / {np.median(v):.3f} / {np.mean(np.array(v) <= 5):.2f}"
                           for v in errors.values())
        lines.append(f"| {setting} | {cells} | {within} of {good} ({by_data}) |")
        print(lines[-1], flush=True)
    table = "\n".join(lines) + "\n"
    if args.out:
        with open(args.out, "w") as f:
            f.write(table)


if __name__ == "__main__":
    main()
