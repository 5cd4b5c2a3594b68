"""Clouds far apart in the caller's frame: a pair of dragon scans with the target moved further and further off.

    python scripts/check_far_apart.py                  # dragon scans 0 -> 24 degrees (../shared)
    python scripts/check_far_apart.py --modelnet ../shared/data/modelnet40_ply_hdf5_1024   # and a few radii apart

Registers the pair as users call it (`registration.load(centring=...)`, ICP and the agreement verdict), the
target moved along x by 0-1,000,000 times the source's extent, with each centring (`shared`: both clouds on
their common centroid, as before 2026-12-01; `separate`; `auto`, the default since). Prints a markdown table
of the rotation error against the truth, the translation error over the extent, the verdict and the seconds.
With ``--modelnet``, also disjoint halves of the first 24 ModelNet40 test shapes (scaled to a radius of about 2,
turned 20, -15 and 10 degrees, moved 0.6, 1.8 or 5.9 units: about 0.3, 0.9 and 3 radii) with "shared" and
"separate": the network alone and with ICP (one direction), median error and share within 5 degrees.
"""

import argparse
import datetime

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", default="../shared/data/stanford_dragon_stand")
    parser.add_argument("--shifts", type=float, nargs="+", default=[0.0, 0.5, 2.0, 30.0, 1000.0, 1e6],
                        help="target offsets in units of the source's extent")
    parser.add_argument("--modelnet", default=None, help="a ModelNet40 h5 folder: also the few-radii table")
    args = parser.parse_args()

    from dit_jax import geometry, registration
    from dit_jax.data import scans

    pair = scans.scan_pairs(scans.load_scans(args.scans), skip=1)[0]
    extent = float(np.ptp(pair.source, axis=0).max())
    print(f"{datetime.date.today().isoformat()}: {pair.name}, the target moved along x; shipped weights, ICP, "
          f"agreement verdict\n")
    print("| centring | offset (source extents) | rotation error (deg) | translation error / extent | verdict | s |"
          "\n|---|---|---|---|---|---|")
    for centring in registration.CENTRINGS:
        model = registration.load(centring=centring)
        model.register(pair.source, pair.target)  # compiles
        for shift in args.shifts:
            offset = np.array([shift * extent, 0.0, 0.0])
            result = model.register(pair.source, pair.target + offset)
            rotation_error = geometry.rotation_angle_deg(result.rotation @ pair.rotation.T)
            translation_error = np.linalg.norm(result.translation - pair.translation - offset) / extent
            print(f"| {centring} | {shift:g} | {rotation_error:.2f} | {translation_error:.4f} | "
                  f"{'trusted' if result.verdict else 'suspect'} | "
                  f"{result.seconds + result.refine_seconds:.1f} |", flush=True)
    if args.modelnet:
        few_radii(args.modelnet)


def few_radii(folder: str) -> None:
    import os

    import h5py

    from dit_jax import geometry, registration
    from dit_jax.data.pairs import euler_zyx_to_matrix

    with h5py.File(os.path.join(folder, "ply_data_test0.h5"), "r") as f:
        shapes = np.asarray(f["data"][:24], np.float64)
    truth = euler_zyx_to_matrix([20.0, -15.0, 10.0])
    print("\n| centring | offset | network: median (deg), within 5 | with ICP: median, within 5 |\n|---|---|---|---|")
    for centring in ("shared", "separate"):
        model = registration.load(n_points=512, verdict_rule="fitness", centring=centring)
        for offset in ([0.5, -0.3, 0.1], [1.5, -1.0, 0.3], [5.0, -3.0, 1.0]):
            errors = {"none": [], "icp": []}
            for shape in shapes:
                src, tgt = shape[0::2] * 2.0, (shape[1::2] * 2.0) @ truth.T + offset
                for refine in errors:
                    rotation = model.register(src, tgt, refine=refine).rotation
                    errors[refine].append(geometry.rotation_angle_deg(rotation @ truth.T))
            cells = [f"{np.median(e):.2f}, {np.mean(np.asarray(e) < 5):.2f}" for e in errors.values()]
            print(f"| {centring} | {np.linalg.norm(offset):.1f} | {cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
