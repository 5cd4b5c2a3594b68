"""Train DIT.

    python train.py                                   # a short run on the embedded furniture set
    python train.py --preset paper --data-dir /data/modelnet40_ply_hdf5_2048 --setting clean
    python train.py --preset cpu --set lr=3e-4 --set model.n_blocks=4 --workdir runs/mine
    python train.py --workdir runs/mine --resume      # continue where a run stopped (even after kill -9),
                                                      # with the config saved in the workdir
    python train.py --preset cpu --setting low_noise_partial --init-from runs/mine/model   # fine-tune
    python train.py --preset cpu --settings clean independent_clean scan_high_noise   # a mix of settings

Every field of the preset can be overridden with --set FIELD=VALUE (fields of dit_jax.training.TrainConfig;
model.FIELD for dit_jax.configs.DITConfig). Several processes (hosts, or GPUs): start one per host with
--distributed and --coordinator HOST:PORT --num-processes N --process-id I (or their JAX_* variables, or a
SLURM allocation); the batch is split over all devices of all processes.
"""

import argparse
import ast
import dataclasses
import json
import os
import sys


def _value(text: str, like=None):
    """``text`` as a Python literal (else the string itself), checked against ``like``, the field's current
    value: a flag takes true/false in any case (never a truthy string such as "false"), a number a number
    (a whole one for a whole-number field)."""
    if isinstance(like, bool):
        word = text.strip().lower()
        if word in ("true", "1", "yes", "on"):
            return True
        if word in ("false", "0", "no", "off"):
            return False
        raise ValueError(f"expected true or false, got {text!r}")
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        value = text
    if isinstance(like, (int, float)) and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise ValueError(f"expected a number, got {text!r}")
    if isinstance(like, int) and not isinstance(value, int):
        raise ValueError(f"expected a whole number, got {text!r}")
    return value


def parse(argv=None):
    from dit_jax import compile_cache, training

    parser = argparse.ArgumentParser(description="Train DIT (see the module docstring for examples).")
    parser.add_argument("--preset", default=None, choices=sorted(training.PRESETS),
                        help="default: quick, or with --resume the config saved in the workdir")
    parser.add_argument("--workdir", default=None, help="default: runs/<preset>-<setting>")
    parser.add_argument("--data-dir", default=None, help="ModelNet40 in the h5 layout (default: embedded set)")
    from dit_jax.data import pairs

    parser.add_argument("--setting", default=None, choices=list(pairs.SETTINGS))
    parser.add_argument("--settings", nargs="+", default=None, choices=list(pairs.SETTINGS), metavar="SETTING",
                        help="train on a mix of these settings (repeat one to draw it more often); --setting "
                             "defaults to the first")
    parser.add_argument("--unseen", action="store_true", help="train on categories 0-19 only")
    parser.add_argument("--variant", default=None, choices=["authors", "peers"])
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--init-from", default=None, metavar="MODEL_DIR",
                        help="start from these params (a model checkpoint, e.g. runs/x/model): fine-tuning; "
                             "with --set model.n_blocks above the checkpoint's, its PFT is grown in depth "
                             "(new layers start as identities)")
    parser.add_argument("--prepared-dir", default=None, help="where TFDS keeps prepared data")
    parser.add_argument("--distributed", action="store_true",
                        help="join a multi-process run (one process per host or per GPU; see the README)")
    parser.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                        help="with --distributed: process 0's address (default: $JAX_COORDINATOR_ADDRESS or "
                             "the cluster's)")
    parser.add_argument("--num-processes", type=int, default=None,
                        help="with --distributed (default: $JAX_NUM_PROCESSES or the cluster's)")
    parser.add_argument("--process-id", type=int, default=None,
                        help="with --distributed (default: $JAX_PROCESS_ID or the cluster's)")
    parser.add_argument("--no-progress", action="store_true")
    compile_cache.add_arguments(parser)
    args = parser.parse_args(argv)

    preset = args.preset or "quick"
    config = training.PRESETS[preset]
    saved = os.path.join(args.workdir or "", "train_config.json")
    if args.resume and args.preset is None and args.workdir and os.path.exists(saved):
        with open(saved) as f:
            config = training.TrainConfig.from_json(json.load(f))
    changes, model_changes = {}, dict(config.model_overrides)
    for name, value in (("data_dir", args.data_dir), ("setting", args.setting), ("variant", args.variant)):
        if value is not None:
            changes[name] = value
    if args.settings:
        changes["settings"] = tuple(args.settings)
        changes.setdefault("setting", args.settings[0])
    if args.unseen:
        changes["unseen"] = True
    if args.init_from:
        changes["init_from"] = os.path.abspath(args.init_from)
    fields = {f.name for f in dataclasses.fields(training.TrainConfig)}
    for item in args.set:
        key, sep, text = item.partition("=")
        if not sep:
            parser.error(f"--set {item!r}: expected FIELD=VALUE")
        try:
            if key.startswith("model."):
                name = key[len("model."):]
                model_changes[name] = _value(text, getattr(config.model_config(), name, None))
            elif key in fields:
                changes[key] = _value(text, getattr(config, key))
            else:
                parser.error(f"--set {key}: no such field (fields: {', '.join(sorted(fields))}, model.*)")
        except ValueError as err:
            parser.error(f"--set {key}: {err}")
    changes["model_overrides"] = tuple(sorted(model_changes.items()))
    try:
        config = dataclasses.replace(config, **changes)
        config.model_config()
    except (TypeError, ValueError) as err:
        parser.error(str(err))
    workdir = args.workdir or f"runs/{preset}-{'mix' if config.settings else config.setting}"
    return args, config, workdir


def main(argv=None) -> int:
    args, config, workdir = parse(argv)
    from dit_jax import compile_cache, training

    if args.distributed:
        training.initialize_distributed(args.coordinator, args.num_processes, args.process_id)

    compile_cache.from_args(args)
    from dit_jax.data.shapes import DataError

    try:
        result = training.train(config, workdir, resume=args.resume, prepared_dir=args.prepared_dir,
                                 progress=not args.no_progress)
    except (DataError, training.TrainCheckpointError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
