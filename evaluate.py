"""Evaluate a DIT checkpoint beside classical baselines on the same test pairs.

    python evaluate.py                                    # the shipped weights, embedded set
    python evaluate.py --checkpoint runs/quick-clean/model  # what `python train.py` trained
    python evaluate.py --checkpoint runs/clean/model --data-dir /data/modelnet40_ply_hdf5_2048 \\
        --settings all --unseen --baselines icp fpfh_ransac fgr fpfh_ransac_icp fgr_icp
    python evaluate.py --scans ../shared/data/stanford_dragon_stand --baselines fpfh_ransac   # real scans
    python evaluate.py --data-dir /data/modelnet40_ply_hdf5_2048 --unseen --angle-sweep   # error vs angle
    python evaluate.py --scenes ../shared/data/3dmatch --baselines open3d_multiway --out eval_scenes  # whole scenes

Settings: the authors' three (clean, low_noise_partial, high_noise_partial; both clouds made of the same
points) and those whose clouds share no point, as real data (independent_*, scan_*; dit_jax.data.pairs).
"authors" picks the first three, "all" every one. With --scans, a folder of real scans with their poses gives
the pairs: a Stanford .conf (scan i with scan i + SKIP, --skips), 3DMatch fragments with gt.log lists, a
KITTI poses.txt, or source.* and target.* with T_target_source.txt (dit_jax.data.scans).

Methods, from the registration pipeline: the network alone (DIT), the network refined (DIT+ICP: ICP on
sparse clouds, GICP on scans; --refine sets it, none drops the row) and the default pipeline (pipeline: on
scans, local features both ways first, the network where they disagree; elsewhere DIT+ICP; --features off
drops it); beside them the --baselines, each at the options tuned for the setting on validation pairs
(docs/baselines_tuning.md). With --scans three more rows may be asked for: open3d_room_5cm, Open3D's tutorial
recipe for rooms in metres as it stands; open3d_room_full, the same at full strength (normals facing the sensor,
RANSAC to confidence 0.9999, ICP within 4 cm); and features, the pipeline's registration by local features alone. A folder of
3DMatch scenes gives the benchmark's registration recall per list and per scene (dit_jax.data.scans). With
--scenes, the one baseline is open3d_multiway, Open3D's multiway registration of the whole scene at full
strength; its pairs are logged in --out as they finish (open3d_multiway_SCENE.jsonl), and a run given the same
--out takes the logged ones and registers the rest.

Writes results.md, results.json, success_ratio.png, registrations.png and worst_<setting>.png (each method's
worst pair) to --out.
"""

import argparse
import sys

# What each mode leaves out, so that a flag given with it is refused rather than silently ignored.
#: The flags of the synthetic pairs' tables, which real scans and scenes do not take.
_TABLES_ONLY = ("angle_sweep", "data_dir", "settings", "unseen", "variant", "authors_thresholds", "batch_size", "reuse")
_IGNORED_BY = {
    "--scenes": (*_TABLES_ONLY, "skips", "max_pairs", "no_dit"),
    "--scans": (*_TABLES_ONLY, "scenes", "verdict"),
    "--angle-sweep": (
        "scenes",
        "skips",
        "features",
        "variant",
        "iters",
        "gmcce_threshold",
        "authors_thresholds",
        "baselines",
        "batch_size",
        "bfloat16",
        "reuse",
        "verdict",
        "best_direction",
        "no_dit",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    """evaluate.py's command line."""
    from dit_jax.data.pairs import SETTINGS
    from dit_jax.evaluators.baselines import SCAN_BASELINES
    from dit_jax.evaluators.scene_baselines import SCENE_BASELINES
    from dit_jax.network import compile_cache
    from dit_jax.pipeline import settings as inference_settings

    parser = argparse.ArgumentParser(description="Evaluate DIT and baselines (see the module docstring).")
    parser.add_argument(
        "--checkpoint", default=None, help="a model checkpoint directory (default: the weights that ship with dit-jax)"
    )
    parser.add_argument("--no-dit", action="store_true", help="evaluate the baselines alone")
    parser.add_argument("--data-dir", default=None, help="ModelNet40 in the h5 layout (default: embedded set)")
    parser.add_argument("--settings", nargs="+", default=["clean"], choices=tuple(SETTINGS) + ("authors", "all"))
    parser.add_argument(
        "--scans",
        default=None,
        metavar="DIR",
        help="evaluate on real scans with known poses instead of shapes: a Stanford .conf, "
        "3DMatch gt.log lists, a KITTI poses.txt or T_target_source.txt",
    )
    parser.add_argument(
        "--scenes",
        default=None,
        metavar="DIR",
        help="place each 3DMatch scene's fragments by a pose graph (dit_jax.scenes.scene) and score every benchmark "
        "pair from the placed poses, beside the pairwise results: a folder of scene folders, or one",
    )
    parser.add_argument(
        "--angle-sweep",
        action="store_true",
        help="DIT's error against rotation angles 0-180 degrees on the first --settings setting "
        "(default independent_clean) instead of the tables",
    )
    parser.add_argument(
        "--skips",
        nargs="+",
        type=int,
        default=[1, 2],
        help="with --scans of a series: pair scan i with scan i + SKIP (default: 1 2)",
    )
    parser.add_argument("--unseen", action="store_true", help="test on categories 20-39")
    parser.add_argument("--variant", default="authors", choices=["authors", "peers"])
    inference_settings.add_flags(
        parser,
        (
            "points",
            "iters",
            "gmcce_threshold",
            "bfloat16",
            "refine",
            "features",
            "viewpoint",
            "descriptor",
            "verdict",
            "best_direction",
        ),
    )
    parser.add_argument("--max-pairs", type=int, default=None, help="only the first pairs of each setting")
    parser.add_argument(
        "--authors-thresholds",
        action="store_true",
        help="run each setting at the authors' GMCCE threshold for it (their paper's table) instead of the "
        "model's own, the same for every input",
    )
    parser.add_argument("--baselines", nargs="*", default=[], choices=(*SCAN_BASELINES, *SCENE_BASELINES))
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--out", default="eval")
    parser.add_argument(
        "--reuse",
        default=None,
        metavar="DIR",
        help="take baselines scored on the same pairs from an earlier --out instead of rerunning them",
    )
    parser.add_argument("--no-progress", action="store_true")
    compile_cache.add_arguments(parser)
    return parser


def main(argv=None) -> int:
    from dit_jax.data.pairs import AUTHORS_SETTINGS, SETTINGS
    from dit_jax.network import compile_cache
    from dit_jax.pipeline import settings as inference_settings

    parser = build_parser()
    args = parser.parse_args(argv)
    mode = "--scans" if args.scans else "--scenes" if args.scenes else "--angle-sweep" if args.angle_sweep else None
    for dest in _IGNORED_BY.get(mode, ("skips",)):
        if getattr(args, dest) != parser.get_default(dest):
            flag = "--" + dest.replace("_", "-")
            parser.error(f"{flag} does not apply " + (f"with {mode}" if mode else "without --scans"))
    from dit_jax.evaluators.baselines import NAMES as TUNED_BASELINES
    from dit_jax.evaluators.scene_baselines import SCENE_BASELINES

    untuned = [name for name in args.baselines if name not in TUNED_BASELINES and name not in SCENE_BASELINES]
    if untuned and not args.scans:
        parser.error(f"--baselines {' '.join(untuned)}: only with --scans")
    whole = [name for name in args.baselines if name in SCENE_BASELINES]
    if whole != args.baselines and args.scenes or whole and not args.scenes:
        parser.error(f"--baselines: with --scenes, only {', '.join(SCENE_BASELINES)}, which takes whole scenes")
    chosen = []
    for name in args.settings:
        chosen += list(SETTINGS) if name == "all" else list(AUTHORS_SETTINGS) if name == "authors" else [name]
    settings = tuple(dict.fromkeys(chosen))

    compile_cache.from_args(args)
    from dit_jax import evaluators
    from dit_jax.data.shapes import DataError
    from dit_jax.network.checkpoint import CheckpointError
    from dit_jax.pipeline import registration

    inference = inference_settings.changes(args)
    try:
        checkpoint = None if args.no_dit else args.checkpoint or registration.shipped_weights()
        if args.angle_sweep:
            setting = settings[0] if args.settings != ["clean"] else "independent_clean"
            results = evaluators.angle_sweep(
                checkpoint,
                args.out,
                data_dir=args.data_dir,
                setting=setting,
                unseen=args.unseen,
                pairs_per_angle=args.max_pairs or 24,
                n_points=args.points,
                progress=not args.no_progress,
                refine=args.refine or "icp",
            )
            print(results["table"])
            print(f"wrote {args.out}/angle_sweep.md, angle_sweep.json, angle_sweep.png")
            return 0
        if args.scenes:
            results = evaluators.evaluate_scenes(
                checkpoint,
                args.scenes,
                args.out,
                inference=inference,
                progress=not args.no_progress,
                baselines=args.baselines,
            )
            print(results["table"])
            print(f"wrote {args.out}/results.md, results.json")
            return 0
        if args.scans:
            results = evaluators.evaluate_scans(
                checkpoint,
                args.scans,
                args.out,
                skips=args.skips,
                baselines=args.baselines,
                max_pairs=args.max_pairs,
                progress=not args.no_progress,
                inference=inference,
            )
            print(results["table"])
            print(f"wrote {args.out}/results.md, results.json, success_ratio.png")
            return 0
        results = evaluators.evaluate(
            checkpoint,
            args.out,
            data_dir=args.data_dir,
            settings=settings,
            unseen=args.unseen,
            variant=args.variant,
            max_pairs=args.max_pairs,
            baselines=args.baselines,
            inference=inference,
            authors_thresholds=args.authors_thresholds,
            batch_size=args.batch_size,
            progress=not args.no_progress,
            reuse=args.reuse,
        )
    except (CheckpointError, DataError, ImportError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(results["table"])
    import os

    written = sorted(f for f in os.listdir(args.out) if f.endswith((".md", ".json", ".png")))
    print(f"wrote {', '.join(os.path.join(args.out, f) for f in written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
