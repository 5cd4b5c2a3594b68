"""Exports a training run's best params as the weights that ship with dit-jax (dit_jax/network/weights/ or dit_jax/features/weights/).

    python tools/ship_weights.py runs/mn40-clean --command "python train.py ..." [--out DIR]
    python tools/ship_weights.py runs/mix --command "..." --choice runs/mix/choice.json
    python tools/ship_weights.py runs/features-all --descriptor --command "python train.py --config configs/features.py ..."

Writes a model checkpoint (dit_jax.network.checkpoint) whose ``extra`` records what a user needs to trust it: the
training command and config, the data, the step chosen and how, the steps run, the summed step time from
the run's metrics.jsonl, its last validation figures, and its inference settings
(:class:`dit_jax.pipeline.settings.InferenceSettings`, 1000 points per cloud as in the authors' test protocol).
``--choice`` (the output of ``python tools/calibrate.py``) is then recorded into those settings as ``python tools/calibrate.py
--record`` records one.
A run that started from other weights (``init_from``) keeps their record under ``trained_from``, so the whole
history travels with the weights.

``--descriptor`` ships a learned descriptor's run instead (``python train.py --config configs/features.py``):
its ``descriptor/`` weights, with the command added to their record, as dit_jax/features/weights/descriptor-rooms.
"""

import argparse
import json
import os
import shutil

import calibrate

from dit_jax import training
from dit_jax.features import network
from dit_jax.network import checkpoint
from dit_jax.pipeline import registration
from dit_jax.pipeline.settings import InferenceSettings


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python tools/ship_weights.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("workdir")
    parser.add_argument("--command", required=True, help="the command(s) that trained it, for the record")
    parser.add_argument("--out", default=None, help="default: where the package's shipped weights of the kind live")
    parser.add_argument("--descriptor", action="store_true", help="ship a learned descriptor's run")
    parser.add_argument("--inference-points", type=int, default=1000)
    parser.add_argument("--note", default="", help="anything else a user should know (pauses, resumes)")
    parser.add_argument(
        "--choice",
        default=None,
        help="inference settings and verdict threshold to ship (python tools/calibrate.py's output)",
    )
    args = parser.parse_args(argv)
    if args.descriptor:
        ship_descriptor(args.workdir, args.command, args.out or network.SHIPPED)
        return
    args.out = args.out or registration.shipped_weights()

    records = [json.loads(line) for line in open(os.path.join(args.workdir, "metrics.jsonl"))]
    train = [r for r in records if r.get("split") == "train"]
    val = [r for r in records if r.get("split") == "val"]
    log_every = training.TrainConfig.from_json(
        json.load(open(os.path.join(args.workdir, "train_config.json")))
    ).log_every
    # metrics.jsonl may hold a step twice after a resume; count each logged step once
    per_step = {r["step"]: r["seconds_per_step"] for r in train}
    staging = args.out + ".new"
    if os.path.exists(staging):
        shutil.rmtree(staging)
    path = training.export_params(args.workdir, staging)
    extra = checkpoint.read_extra(path)
    extra.update(
        {
            "command": args.command,
            "steps_run": max(per_step) if per_step else 0,
            "train_seconds": round(sum(per_step.values()) * log_every),
            "last_validation": val[-1] if val else None,
            registration.SETTINGS_KEY: InferenceSettings(n_points=args.inference_points).to_dict(),
            "note": args.note,
        }
    )
    params, config = checkpoint.restore(path)
    init_from = extra.get("train_config", {}).get("init_from")
    if init_from and os.path.isdir(init_from):
        extra["trained_from"] = checkpoint.read_extra(init_from)
    extra = portable(extra, extra.get("train_config", {}).get("data_dir"))
    shutil.rmtree(staging)
    if os.path.exists(args.out):
        shutil.rmtree(args.out)
    checkpoint.save(args.out, params, config, extra=extra)
    _unmark(args.out)
    if args.choice:
        calibrate.record(args.out, json.load(open(args.choice)))
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(args.out) for f in fs)
    print(f"wrote {args.out} ({size / 2**20:.1f} MB): step {extra['step']} chosen by {extra['chosen_by']}")


def _unmark(directory: str) -> None:
    """orbax's commit markers name the folder they were written in; what ships names no machine's folder."""
    for root, _, files in os.walk(directory):
        if "commit_success.txt" in files:
            with open(os.path.join(root, "commit_success.txt"), "w") as f:
                f.write("Checkpoint commit was successful")


def ship_descriptor(workdir: str, command: str, out: str) -> None:
    """The learned descriptor of the run in ``workdir`` written to ``out``, its record naming ``command``."""
    found = network.load(os.path.join(workdir, "descriptor"))
    if os.path.exists(out):
        shutil.rmtree(out)
    network.save(out, found._replace(extra={**found.extra, "command": command}))
    _unmark(out)
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs)
    print(f"wrote {out} ({size / 2**20:.2f} MB): trained on {', '.join(found.extra.get('scenes', []))}")


def portable(record, data_dir: str | None):
    """``record`` with every mention of the training machine's ModelNet40 folder ``data_dir`` written
    ``$MODELNET40``, as the docs name it: the shipped records hold no path of one machine."""
    if not data_dir:
        return record
    if isinstance(record, dict):
        return {key: portable(value, data_dir) for key, value in record.items()}
    if isinstance(record, list):
        return [portable(value, data_dir) for value in record]
    if isinstance(record, str):
        return record.replace(os.path.normpath(data_dir), "$MODELNET40").replace(data_dir, "$MODELNET40")
    return record


if __name__ == "__main__":
    main()
