"""Would DIT's refinement end nearer the truth if it chose among its ICP runs by a point-to-plane fit?

:func:`dit_jax.icp.refine` keeps, among its runs, the motion with the lowest :func:`dit_jax.icp.trimmed_fit`
(squared point-to-point distances of the closest 70 % of the source points). Where the clouds share no point,
that distance is biased by the sampling; the distance to the target's tangent plane at the nearest point is
not. This script runs ``refine`` from the shipped network's estimates on validation pairs of training shapes
twice, once as it ships and once with ``icp.trimmed_fit`` replaced by the same trimmed mean over plane
distances (normals from :func:`dit_jax.icp.estimate_normals`), and prints per setting: rotation error (median,
mean, share within 1 and 5 degrees), how many pairs DIT had within 10 degrees end within 1, and on how many
pairs the true motion scores better than the result by that selection's own fit.

    python scripts/check_refinement_selection.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --pairs 48
"""
import argparse
import time

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from dit_jax import checkpoint, icp, model, registration, training
from dit_jax.data.pairs import SETTINGS
from dit_jax.geometry import rotation_angle_deg

original = icp.trimmed_fit
_normals = {}  # the target's normals, per k-d tree, for one pair at a time

def plane_fit(src, tree, rotation, translation, *, share=icp.FIT_SHARE, seed=0, max_points=5_000, cap=None):
    """:func:`dit_jax.icp.trimmed_fit`'s contract, scored by squared distances to the target's tangent planes
    (the closest ``share`` of the source points by point distance, so a partial view's extra parts still
    do not count)."""
    if len(src) > max_points:
        src = src[np.random.default_rng(seed).choice(len(src), max_points, replace=False)]
    key = id(tree)
    if key not in _normals:
        _normals[key] = icp.estimate_normals(tree.data, tree=tree)
    normals = _normals[key]
    translation = np.asarray(translation, np.float64)
    moved = (src @ rotation.T)[None] + np.reshape(translation, (-1, 1, 3))
    bound = np.inf if cap is None else cap
    gaps, idx = tree.query(moved.reshape(-1, 3), distance_upper_bound=bound)
    idx = np.minimum(idx, len(tree.data) - 1)
    plane = np.abs(np.sum((moved.reshape(-1, 3) - tree.data[idx]) * normals[idx], axis=1))
    plane = np.where(np.isfinite(gaps), plane, bound)
    gaps = np.minimum(gaps, bound).reshape(len(moved), -1)
    plane = plane.reshape(len(moved), -1)
    k = max(1, int(share * src.shape[0]))
    order = np.argsort(gaps, axis=1)[:, :k]
    scores = np.mean(np.take_along_axis(plane, order, axis=1) ** 2, axis=1)
    return scores if translation.ndim == 2 else float(scores[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--pairs", type=int, default=48, help="validation pairs per setting (categories 0-19)")
    args = parser.parse_args()
    settings = [s for s in SETTINGS if SETTINGS[s].independent] + ["high_noise_partial"]
    batches = training.validation_batches(args.data_dir, settings, count=args.pairs, unseen=True)
    params, config = checkpoint.restore(registration.shipped_weights())
    for setting, b in batches.items():
        R, t, _ = model.register(params, jnp.asarray(b["src"]), jnp.asarray(b["tgt"]), config)
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
        errs = {"dit": [], "point": [], "plane": [], "truth_better_point": [], "truth_better_plane": []}
        secs = {"point": 0.0, "plane": 0.0}
        for i in range(len(b["src"])):
            src, tgt = b["src"][i].astype(np.float64), b["tgt"][i].astype(np.float64)
            errs["dit"].append(rotation_angle_deg(R[i].T @ b["R"][i]))
            for name, fn in (("point", original), ("plane", plane_fit)):
                icp.trimmed_fit = fn
                _normals.clear()
                s0 = time.perf_counter()
                r = icp.refine(src, tgt, R[i], t[i])
                secs[name] += time.perf_counter() - s0
                errs[name].append(rotation_angle_deg(r.rotation.T @ b["R"][i]))
                tree = cKDTree(tgt)
                truth = fn(src, tree, b["R"][i].astype(np.float64), b["t"][i].astype(np.float64))
                got = fn(src, tree, r.rotation, r.translation)
                errs["truth_better_" + name].append(truth < got)
            icp.trimmed_fit = original
        e = {k: np.asarray(v) for k, v in errs.items()}
        near = e["dit"] <= 10

        def row(name):
            x = e[name]
            return (f"{name}: median {np.median(x):.3f} mean {x.mean():.2f} w1 {np.mean(x <= 1):.2f} "
                    f"w5 {np.mean(x <= 5):.2f} | dit<=10 -> <=1: {int((x[near] <= 1).sum())}/{int(near.sum())}")
        print(setting, "|", row("dit"), "|", row("point"), "|", row("plane"),
              f"| truth fits better: point {int(e['truth_better_point'].sum())}, "
              f"plane {int(e['truth_better_plane'].sum())} | s {secs['point']:.0f}/{secs['plane']:.0f}", flush=True)


if __name__ == "__main__":
    main()
