"""``dit-register --pairs LIST``: a list of pairs through one loaded model, each result appended to the
``--results`` log, which a rerun resumes from; ``--shard I/N`` takes every N-th pair."""

from __future__ import annotations

import json
import os
import re
import sys
import warnings

from dit_jax import io
from dit_jax.cli import files


def read_pair_list(path: str) -> list[tuple[str, str]]:
    """The (source, target) paths of a pair list: 'SRC TGT' a line, blank lines and '#' comments skipped,
    relative paths taken from the list's folder. Raises ValueError naming the line that is not a pair."""
    folder = os.path.dirname(os.path.abspath(path))
    pairs = []
    if not os.path.isfile(path):
        raise ValueError(f"--pairs {path}: " + ("is a folder" if os.path.isdir(path) else "no such file"))
    with open(path) as f:
        for number, line in enumerate(f, 1):
            fields = line.split("#", 1)[0].split()
            if not fields:
                continue
            if len(fields) != 2:
                raise ValueError(f"{path}, line {number}: expected 'SRC TGT', got {line.strip()!r}")
            pairs.append(tuple(os.path.join(folder, field) for field in fields))
    if not pairs:
        raise ValueError(f"{path}: no pairs in the list")
    return pairs


def shard(text: str | None) -> tuple[int, int]:
    if text is None:
        return 0, 1
    match = re.fullmatch(r"(\d+)/(\d+)", text.strip())
    if not match or not int(match.group(1)) < int(match.group(2)):
        raise ValueError(f"--shard {text}: expected I/N with 0 <= I < N, such as 0/4")
    return int(match.group(1)), int(match.group(2))


def register_pair(model, args, src_path: str, tgt_path: str) -> dict:
    """One pair of the list registered: the result's JSON fields (and its warnings), or ``{"error": ...}``."""
    from dit_jax.pipeline import sampling

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", sampling.SizeMismatchWarning)
            result = model.register(files.read_cloud(src_path, args), files.read_cloud(tgt_path, args))
    except sampling.InputError as err:  # name the files, not "source"/"target"
        message = str(err).replace("source:", f"{src_path}:", 1).replace("target:", f"{tgt_path}:", 1)
        return {"error": " ".join(message.split())}
    except (io.CloudFileError, ValueError, OSError) as err:
        return {"error": " ".join(str(err).split())}
    record = result.to_json()
    if problems := files.warning_lines(caught, src_path, tgt_path):  # kept with the pair, not on stderr
        record["warnings"] = problems
    return record


def register_list(args, pairs: list[tuple[str, str]], shard: tuple[int, int], model_kwargs: dict) -> int:
    """``--pairs``: the ``pairs`` of shard (index, count) through one loaded model; returns the exit status.

    With --results, a pair whose identity and settings already have a finished record is skipped; each pair
    is worked on under its lock, so processes sharing the file never register one pair twice."""
    from tqdm.auto import tqdm

    from dit_jax.cli import results_log
    from dit_jax.pipeline import registration

    index, count = shard
    chosen = [(k, pair) for k, pair in enumerate(pairs) if k % count == index]
    key = results_log.settings_key(args.checkpoint, model_kwargs, files.reading_key(args))
    identities = {k: results_log.identity(*pair) for k, pair in chosen}
    log = files.open_results(args, pairs, key)
    latest: dict[int, dict] = {}
    by_identity: dict[str, list[int]] = {}
    for k, pair in identities.items():  # a list may name one pair twice: one result serves both
        by_identity.setdefault(results_log.identity_key(pair), []).append(k)

    def take(records: list[dict]) -> None:  # the newest record of each chosen pair, finished ones first
        for record in records:
            if record.get("settings") != key:
                continue
            for k in by_identity.get(results_log.identity_key(record.get("pair")), ()):
                if results_log.finished(record) or not results_log.finished(latest.get(k, {})):
                    latest[k] = record

    def done(k: int) -> bool:
        return results_log.finished(latest.get(k, {}))

    if log is not None:
        take(log.records)
    model = registration.load(args.checkpoint, **model_kwargs)
    bar = tqdm(
        total=len(chosen),
        initial=sum(map(done, identities)),
        desc="pairs",
        unit="pair",
        file=sys.stderr,
        disable=args.no_progress,
        dynamic_ncols=True,
    )

    def run(k: int, src_path: str, tgt_path: str) -> None:
        record = {"index": k, "src": src_path, "tgt": tgt_path, "pair": identities[k], "settings": key}
        record |= register_pair(model, args, src_path, tgt_path)
        if log is None:
            print(json.dumps(record), flush=True)
        else:
            log.append(record)
        take([record])
        bar.update(1)

    try:
        waiting = []
        for k, (src_path, tgt_path) in chosen:
            if done(k):
                continue
            if log is None:
                run(k, src_path, tgt_path)
                continue
            with log.pair_lock(k, wait=False) as mine:
                if not mine:  # another process is on it: come back once the rest is done
                    waiting.append((k, src_path, tgt_path))
                    continue
                take(log.read_new())
                if not done(k):
                    run(k, src_path, tgt_path)
        for k, src_path, tgt_path in waiting:
            with log.pair_lock(k, wait=True):
                take(log.read_new())
                if not done(k):
                    run(k, src_path, tgt_path)
    finally:
        bar.close()
        if log is not None:
            log.close()
    return list_status(args, [latest.get(k, {}) for k in identities])


def list_status(args, records: list[dict]) -> int:
    """The exit status of a list from each chosen pair's newest record: 2 where one has no result, else 3
    where one is probably wrong (0 with --no-verdict-status), else 0."""
    errors = sum(not r or "error" in r for r in records)
    wrong = sum(r.get("level") == "probably wrong" for r in records)
    if errors:
        print(
            f"{files.PROG}: error: {errors} of {len(records)} pairs could not be registered (their lines say why)",
            file=sys.stderr,
        )
        return 2
    if wrong:
        print(f"{files.PROG}: warning: {wrong} of {len(records)} results are probably wrong", file=sys.stderr)
        return 0 if args.no_verdict_status else files.EXIT_SUSPECT
    return 0
