"""How the network should sample a scan: farthest-point sampling over the whole cloud (the pipeline's) against a
uniform random sample, the network alone, on real scans with known poses.

    python benchmarks/scene_sampling.py ../shared/data/3dmatch_redkitchen ../shared/data/lidar_pair \\
        ../shared/data/stanford_dragon_stand

For each pair, each sampler picks the shipped settings' point count from each cloud (farthest-point sampling
from a seeded random pool, as dit_jax.sampling.sample_and_normalise does; or a seeded uniform random
subset); the pipeline's own stages then normalise (normalise) and run the network one way
(network). Prints one JSON record per pair set and sampler (median rotation error, pairs within
5 degrees), then a Markdown table.
"""

import argparse
import datetime
import json
import os

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scans", nargs="+", help="folders of scans with known poses")
    args = parser.parse_args()

    from dit_jax import geometry, registration
    from dit_jax.data import scans as scans_lib
    from dit_jax.network_stage import network
    from dit_jax.sampling import farthest_point_sample, normalise

    model = registration.load()
    settings = model.settings
    samplers = {
        "farthest-point": lambda cloud, seed: farthest_point_sample(
            cloud, settings.n_points, seed=seed, pool=settings.fps_pool
        ),
        "uniform random": lambda cloud, seed: np.sort(
            np.random.default_rng(seed).choice(len(cloud), min(settings.n_points, len(cloud)), replace=False)
        ),
    }
    records = []
    for folder in args.scans:
        for set_name, found in scans_lib.load_pair_sets(folder).items():
            for sampler, pick in samplers.items():
                errors = []
                for pair in found.pairs:
                    src = pair.source[pick(pair.source, settings.seed)]
                    tgt = pair.target[pick(pair.target, settings.seed + 1)]
                    src_n, tgt_n, src_c, tgt_c, scale = normalise(src, tgt, settings.centring)
                    rotation = network(
                        model.params, model.config, src_n[None].astype(np.float32), tgt_n[None].astype(np.float32)
                    ).rotation
                    errors.append(geometry.rotation_angle_deg(rotation[0].T @ pair.rotation))
                errors = np.asarray(errors)
                record = {
                    "benchmark": "scene_sampling",
                    "date": datetime.date.today().isoformat(),
                    "data": os.path.basename(os.path.normpath(folder)),
                    "set": set_name,
                    "sampler": sampler,
                    "pairs": len(errors),
                    "median_deg": float(np.median(errors)),
                    "within_5": int(np.sum(errors <= 5.0)),
                }
                print(json.dumps(record), flush=True)
                records.append(record)
    print(
        "\n| data | sampler | pairs | network alone: median rotation error (deg) | within 5 deg |\n"
        "|---|---|---|---|---|"
    )
    for r in records:
        print(f"| {r['data']} {r['set']} | {r['sampler']} | {r['pairs']} | {r['median_deg']:.2f} | {r['within_5']} |")


if __name__ == "__main__":
    main()
