"""``register(..., rotation_search=True)`` against ``register`` as it ships, on pairs re-posed at rotations of
0 to 180 degrees about random axes: the share within 5 degrees per angle, and the start margin's choice.

    # choose the margin (icp.START_MARGIN) on validation pairs of training shapes, never test pairs
    python scripts/check_rotation_search.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --split val \\
        --pairs 8 --margins-only --save runs/search_val.json
    # measure on test pairs (unseen categories) and on real scans, DIT+ICP with and without the search
    python scripts/check_rotation_search.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --split test \\
        --pairs 16 --save runs/search_test.json
    python scripts/check_rotation_search.py --scans ../shared/data/stanford_dragon_stand --skips 1 2 3 4 6

Each ModelNet40 pair is taken back to its shape's frame and re-posed at exactly each angle (as evaluate.py's
``--angle-sweep``). ``--margins-only`` runs the network from the 24 turned starts (forward only, no
refinement) and records every start's :func:`dit_jax.icp.start_scores` score and the rotation error where its
short ICP ends; the table then gives, per margin, the share within 5 degrees of the start
:func:`dit_jax.icp.best_start` would keep. Without it, each pair is registered twice as users get it (the
shipped verdict, ICP, both directions): as shipped, and with ``rotation_search=True``. Prints markdown.
"""

import argparse
import datetime
import json
import time

import numpy as np

from dit_jax import evaluation, geometry, icp, registration, training
from dit_jax.data import pairs as pairs_lib
from dit_jax.data import scans as scans_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.geometry import rotation_angle_deg

MARGINS = (1.0, 0.95, 0.9, 0.8, 0.7, 0.5, 0.0)


def _modelnet_pairs(args, n_points):
    """Yields (label, angle, src, tgt, true rotation) for each setting, angle and pair."""
    if args.split == "val":
        batches = training.validation_batches(args.data_dir, args.settings, count=args.pairs, n_points=n_points)
    else:
        shapes = shapes_lib.load_shapes(args.data_dir, "test",
                                        n_points=pairs_lib.shape_points(args.data_dir, n_points, args.settings))
        batches = {}
        for setting in args.settings:
            ds = pairs_lib.PairDataset(shapes, pairs_lib.PairConfig(setting=setting, unseen=True, n_points=n_points))
            batches[setting] = ds.batch(np.linspace(0, len(ds) - 1, args.pairs).astype(int))
    axes = np.random.default_rng(20261201).normal(size=(args.pairs, 3))
    for setting, batch in batches.items():
        for angle in args.angles:
            for i in range(len(batch["src"])):
                in_shape_frame = (batch["tgt"][i] - batch["t"][i]) @ batch["R"][i]
                rotation = geometry.axis_angle_matrix(axes[i], angle)
                yield setting, angle, batch["src"][i], in_shape_frame @ rotation.T + batch["t"][i], rotation


def _scan_pairs(args):
    scans = scans_lib.load_scans(args.scans)
    for skip in args.skips:
        for pair in scans_lib.scan_pairs(scans, skip):
            yield f"skip{skip}", rotation_angle_deg(pair.rotation), pair.source, pair.target, pair.rotation


def _starts_record(model, src, tgt, truth):
    """Every start's score, its network estimate's error and the error where its short ICP ends, for the
    forward direction of one pair."""
    recorded = {}
    original = icp.start_scores

    def recording(points, target, rotations, translations, **kwargs):
        recorded["rotations"] = rotations
        recorded["scores"] = original(points, target, rotations, translations, **kwargs)
        # Where each start's short ICP ends, as start_scores runs it.
        recorded["ended"] = [icp.icp(points, target, r, t, distances=icp.START_DISTANCES, max_points=500,
                                     seed=kwargs.get("seed", 0)).rotation for r, t in zip(rotations, translations)]
        return recorded["scores"]

    icp.start_scores = recording
    try:
        model.register(src, tgt, refine="none", rotation_search=True)
    finally:
        icp.start_scores = original
    # The recorded motions are in the normalised frame, whose rotations are the caller's.
    error = lambda rotations: [rotation_angle_deg(r.T @ truth) for r in rotations]
    return {"scores": recorded["scores"].tolist(), "errors": error(recorded["ended"]),
            "network_errors": error(recorded["rotations"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", help="ModelNet40 in the h5 layout")
    parser.add_argument("--split", choices=("val", "test"), default="val",
                        help="validation pairs of training shapes (categories 0-19) or unseen test pairs")
    parser.add_argument("--settings", nargs="+", default=["independent_clean", "independent_high_noise_partial",
                                                          "scan_low_noise"])
    parser.add_argument("--angles", nargs="+", type=float, default=[0, 30, 60, 90, 120, 150, 180])
    parser.add_argument("--pairs", type=int, default=8, help="pairs per setting (each at every angle)")
    parser.add_argument("--scans", help="a directory of scans with a Stanford .conf (instead of ModelNet40)")
    parser.add_argument("--skips", nargs="+", type=int, default=[1, 2, 3, 4])
    parser.add_argument("--margins-only", action="store_true",
                        help="record the starts' scores and choose the margin; no full registration")
    parser.add_argument("--save", help="write every pair's figures here (JSON)")
    args = parser.parse_args()
    if not args.scans and not args.data_dir:
        parser.error("give --data-dir or --scans")

    # One direction only where the starts are recorded (the backward registration would overwrite them).
    model = registration.load(verdict_rule="fitness") if args.margins_only else registration.load()
    pairs = _scan_pairs(args) if args.scans else _modelnet_pairs(args, model.n_points)
    rows = []
    for label, angle, src, tgt, truth in pairs:
        row = {"set": label, "angle": float(angle)}
        if args.margins_only:
            row.update(_starts_record(model, src, tgt, truth))
        else:
            for name, search in (("shipped", False), ("search", True)):
                started = time.perf_counter()
                result = model.register(src, tgt, rotation_search=search)
                row[name] = rotation_angle_deg(result.rotation.T @ truth)
                row[name + "_seconds"] = time.perf_counter() - started
                row[name + "_trusted"] = bool(result.verdict)
                row[name + "_turn"] = result.start_turn
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if not isinstance(v, list)}), flush=True)
    if args.save:
        with open(args.save, "w") as f:
            json.dump(rows, f)

    source = f"--scans {args.scans} --skips {' '.join(map(str, args.skips))}" if args.scans else (
        f"--data-dir {args.data_dir} --split {args.split} --pairs {args.pairs} --settings {' '.join(args.settings)}")
    print(f"\n{datetime.date.today().isoformat()}: `python scripts/check_rotation_search.py {source}"
          f"{' --margins-only' if args.margins_only else ''}`\n")
    sets = list(dict.fromkeys(r["set"] for r in rows))
    within = lambda errors: f"{np.mean(np.asarray(errors) <= 5):.2f}"
    if args.margins_only:
        angles = sorted({r["angle"] for r in rows})
        print("Share within 5 degrees where the kept start's short ICP ends, per margin (all sets pooled):\n")
        print("| margin | " + " | ".join(f"{a:g} deg" for a in angles) + " | mean |\n|---|" + "---|" * (len(angles) + 1))
        for margin in MARGINS:
            kept = [r["errors"][icp.best_start(r["scores"], margin)] for r in rows]
            per_angle = [np.mean([e <= 5 for e, r in zip(kept, rows) if r["angle"] == a]) for a in angles]
            print(f"| {margin:g} | " + " | ".join(f"{p:.2f}" for p in per_angle) + f" | {np.mean(per_angle):.3f} |")
        best = [min(r["errors"]) for r in rows]
        print(f"\nSome start within 5 degrees after its short ICP: {np.mean(np.asarray(best) <= 5):.2f} of the pairs.")
        return
    print("| set | rotation (deg) | pairs | as shipped: within 5 / median | with the search: within 5 / median | "
          "s per pair (shipped / search) |\n|---|---|---|---|---|---|")
    groups = [(s, a) for s in sets for a in sorted({r["angle"] for r in rows if r["set"] == s})]
    if args.scans:
        groups = [(s, None) for s in sets]
    for s, a in groups:
        chosen = [r for r in rows if r["set"] == s and (a is None or r["angle"] == a)]
        shipped = [r["shipped"] for r in chosen]
        search = [r["search"] for r in chosen]
        angle = (f"{min(r['angle'] for r in chosen):.0f}-{max(r['angle'] for r in chosen):.0f}" if a is None
                 else f"{a:g}")
        print(f"| {s} | {angle} | {len(chosen)} | {within(shipped)} / {np.median(shipped):.2f} | "
              f"{within(search)} / {np.median(search):.2f} | "
              f"{np.median([r['shipped_seconds'] for r in chosen]):.1f} / "
              f"{np.median([r['search_seconds'] for r in chosen]):.1f} |")


if __name__ == "__main__":
    main()
