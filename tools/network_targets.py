"""The network-alone figures a training stage is held to, on test data, for a candidate beside the shipped
weights: a development tool beside the package, not part of it.

    python tools/network_targets.py runs/stage8/model --out runs/stage8/targets.json

Both checkpoints run under the shipped weights' inference settings and model options, unrefined
(`tools/shipping_rule.py`), so that a checkpoint exported from training is
not judged by the authors' GMCCE defaults its config carries. Two figures each, the share within 5 degrees and
the median:

* the first ``--pairs`` independently sampled clean pairs of ModelNet40's unseen categories (test split);
* the Stanford dragon's neighbouring scans (24 degrees apart), from the shared data folder.

The shipping rule (`tools/shipping_rule.py`) decides on validation pairs; these test figures are
what the docs and the model card quote.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import shipping_rule

from dit_jax.data import pairs as pairs_lib
from dit_jax.data import scans as scans_lib
from dit_jax.data import shapes as shapes_lib
from dit_jax.evaluators import common
from dit_jax.geometry import rigid
from dit_jax.pipeline import registration


def errors_deg(registrar: registration.Registrar, pairs: list, rotations: list, batch_size: int) -> np.ndarray:
    """(P,) rotation errors (degrees) of the network's unrefined estimates of ``pairs`` ((src, tgt), ...)."""
    est = common.run_dit(registrar, pairs, batch_size=batch_size)[common.METHOD_DIT]
    return np.array([rigid.rotation_angle_deg(r.T @ t) for r, t in zip(est.rotation, rotations)])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("candidate", help="a model checkpoint (a training run's WORKDIR/model)")
    parser.add_argument("--data-dir", default="../shared/data/modelnet40_ply_hdf5_1024")
    parser.add_argument("--dragon", default="../shared/data/stanford_dragon_stand")
    parser.add_argument("--pairs", type=int, default=100, help="ModelNet40 pairs")
    parser.add_argument("--dragon-pairs", type=int, default=None, help="the first dragon pairs only (default: all)")
    parser.add_argument("--prepared-dir", default=None, help="where TFDS keeps prepared data")
    parser.add_argument("--out", default=None, help="JSON with every figure")
    args = parser.parse_args(argv)

    shipped = registration.load()
    settings = shipping_rule.inference_settings(shipped)
    points = settings.n_points
    shapes = shapes_lib.load_shapes(
        args.data_dir,
        "test",
        data_dir=args.prepared_dir,
        n_points=pairs_lib.shape_points(args.data_dir, points, ["independent_clean"]),
    )
    config = pairs_lib.PairConfig(setting="independent_clean", unseen=True, n_points=points)
    dataset = pairs_lib.PairDataset(shapes, config)
    shape_pairs = [dataset[i] for i in range(min(args.pairs, len(dataset)))]
    dragon = scans_lib.scan_pairs(scans_lib.load_scans(args.dragon), skip=1)[: args.dragon_pairs]
    sets = {
        "independent_clean_unseen": ([(p["src"], p["tgt"]) for p in shape_pairs], [p["R"] for p in shape_pairs], 8),
        "dragon_neighbours": ([(p.source, p.target) for p in dragon], [p.rotation for p in dragon], 1),
    }
    report = {}
    for name, loaded in (("shipped", shipped), ("candidate", registration.load(args.candidate))):
        registrar = registration.Registrar(loaded.params, loaded.checkpoint_config, settings)
        report[name] = {}
        for label, (pairs, rotations, batch_size) in sets.items():
            errors = errors_deg(registrar, pairs, rotations, batch_size)
            report[name][label] = {
                "pairs": len(errors),
                "within_5": int(np.sum(errors <= common.RIGHT_DEG)),
                "median_deg": float(np.median(errors)),
            }
        print(name, json.dumps(report[name]), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
