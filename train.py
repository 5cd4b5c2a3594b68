"""Train DIT, or the learned descriptor of room scans (configs/features.py).

    python train.py                                    # configs/quick.py: a short run on the embedded set
    python train.py --config configs/cpu.py --config.lr=3e-4 --config.model.n_blocks=4 --workdir runs/mine
    python train.py --config configs/paper.py --config.data_dir=/data/modelnet40_ply_hdf5_2048
    python train.py --workdir runs/mine --resume       # continue where a run stopped (even after kill -9),
                                                       # with the config saved in the workdir
    python train.py --config configs/cpu.py --config.setting=low_noise_partial --config.init_from=runs/mine/model
    python train.py --config configs/cpu.py "--config.settings=('clean', 'independent_clean')"   # a mix
    python train.py --config configs/features.py --config.holdout=hotel3   # the learned descriptor of rooms

Recipes are the files in configs/ (configs/shipped/ holds every run that made the shipped weights). Any field
of dit_jax.training.TrainConfig changes with --config.FIELD=VALUE, the network's (dit_jax.network.configs.DITConfig)
with --config.model.FIELD=VALUE. Several processes (hosts, or GPUs): start one per host with --distributed
and --coordinator HOST:PORT --num-processes N --process-id I (or their JAX_* variables, or a SLURM
allocation); the batch is split over all devices of all processes.
"""

import dataclasses
import json
import os
import sys
import types

from absl import flags
from ml_collections import config_flags

CONFIGS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "configs")


def _define_flags() -> flags.FlagValues:
    """train.py's flags, defined afresh for each parse: the recipe's ``--config.FIELD`` flags depend on the
    recipe file and are read from ``sys.argv`` when it loads."""
    values = flags.FlagValues()
    config_flags.DEFINE_config_file(
        "config",
        os.path.join(CONFIGS, "quick.py"),
        "a recipe file (its get_config())",
        flag_values=values,
        lock_config=True,
    )
    flags.DEFINE_string(
        "workdir",
        None,
        "default: runs/<recipe>-<setting>, runs/<recipe>-mix, or runs/features-<holdout or all>",
        flag_values=values,
    )
    flags.DEFINE_bool(
        "resume",
        False,
        "continue the run in --workdir, with the config saved there (unless --config is given)",
        flag_values=values,
    )
    flags.DEFINE_string("prepared-dir", None, "where TFDS keeps prepared data", flag_values=values)
    flags.DEFINE_bool(
        "distributed", False, "join a multi-process run (one process per host or per GPU)", flag_values=values
    )
    flags.DEFINE_string(
        "coordinator",
        None,
        "with --distributed: process 0's address HOST:PORT (default: $JAX_COORDINATOR_ADDRESS or the cluster's)",
        flag_values=values,
    )
    flags.DEFINE_integer(
        "num-processes", None, "with --distributed (default: $JAX_NUM_PROCESSES or the cluster's)", flag_values=values
    )
    flags.DEFINE_integer(
        "process-id", None, "with --distributed (default: $JAX_PROCESS_ID or the cluster's)", flag_values=values
    )
    flags.DEFINE_bool("no-progress", False, "no progress bar", flag_values=values)
    flags.DEFINE_string(
        "compile-cache",
        None,
        "keep compiled XLA programs here (default: $DIT_JAX_COMPILE_CACHE, else ~/.cache/dit-jax/xla)",
        flag_values=values,
    )
    flags.DEFINE_bool("no-compile-cache", False, "compile afresh every run", flag_values=values)
    return values


def _usage_error(message: str):
    print(f"train.py: error: {' '.join(str(message).split())}", file=sys.stderr)
    raise SystemExit(2)


def parse(argv=None):
    """``(options, TrainConfig, workdir)`` from command-line arguments (without the program name); exits 2
    with one line on stderr on a bad flag or value."""
    from dit_jax import training

    argv = sys.argv[1:] if argv is None else list(argv)
    program_argv, sys.argv = sys.argv, ["train.py", *argv]  # the config flag reads its overrides from sys.argv
    try:
        FLAGS = _define_flags()
        if any(arg in ("-h", "--help", "--helpfull") for arg in argv):
            print(__doc__.strip() + "\n\nflags:\n" + FLAGS.get_help(include_special_flags=False))
            raise SystemExit(0)
        FLAGS(sys.argv)
    except (flags.Error, ValueError, TypeError, AttributeError) as err:  # AttributeError: an unknown field
        _usage_error(err)
    finally:
        sys.argv = program_argv
    workdir = FLAGS.workdir
    saved = os.path.join(workdir or "", "train_config.json")
    try:
        if FLAGS.resume and not FLAGS["config"].present and workdir and os.path.exists(saved):
            with open(saved) as f:
                config = training.recipe_from_json(json.load(f))
        else:
            config = training.recipe_from_config_dict(FLAGS.config)
    except (TypeError, ValueError) as err:
        _usage_error(err)
    recipe = os.path.splitext(os.path.basename(config_flags.get_config_filename(FLAGS["config"])))[0]
    if isinstance(config, training.TrainConfig):
        if config.init_from:
            config = dataclasses.replace(config, init_from=os.path.normpath(config.init_from))
        workdir = workdir or f"runs/{recipe}-{'mix' if config.settings else config.setting}"
    else:
        workdir = workdir or f"runs/{recipe}-{config.holdout or 'all'}"
    options = types.SimpleNamespace(
        **{
            name.replace("-", "_"): FLAGS[name].value
            for name in (
                "resume",
                "prepared-dir",
                "distributed",
                "coordinator",
                "num-processes",
                "process-id",
                "no-progress",
                "compile-cache",
                "no-compile-cache",
            )
        }
    )
    return options, config, workdir


def main(argv=None) -> int:
    args, config, workdir = parse(argv)
    from dit_jax import training
    from dit_jax.network import compile_cache

    if args.distributed:
        training.initialize_distributed(args.coordinator, args.num_processes, args.process_id)

    compile_cache.from_args(args)
    from dit_jax.data.shapes import DataError

    try:
        if isinstance(config, training.TrainConfig):
            result = training.train(
                config, workdir, resume=args.resume, prepared_dir=args.prepared_dir, progress=not args.no_progress
            )
        else:
            from dit_jax.training import descriptor

            result = descriptor.train(config, workdir, resume=args.resume, progress=not args.no_progress)
    except (DataError, training.TrainCheckpointError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
