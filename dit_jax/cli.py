"""``dit-register SRC TGT``: register two point-cloud files and print the 4x4 transform moving SRC onto TGT.

    dit-register scan_a.ply scan_b.pcd                    # the shipped weights, refined (GICP on scans)
    dit-register a.xyz b.npy --checkpoint runs/x/model --out a_aligned.ply
    dit-register a.ply b.ply --json > result.json
    dit-register scan_a.ply scan_b.ply --refine none --plot check.png   # the network alone; a picture
    dit-register --pairs pairs.txt --results results.jsonl --shard 0/4   # a list, a quarter of it, resumable

Bad input (a missing, unreadable or malformed file, an unknown format, NaN or Inf values, too few points, not
three coordinates per point, all points identical or on one line) ends with one line on stderr naming the file
and the problem, exit status 2, and no output file. ``--drop-nonfinite`` leaves points with NaN or Inf
coordinates out instead (depth cameras mark pixels without a return so) and says how many. Clouds above
``--max-points`` are read as a random subset of that many points (say ``--no-downsample`` to refuse them
instead). A mesh (a CAD model to find in a scan, say) is read as points sampled uniformly over its surface;
``--out`` with SRC's own extension writes the mesh itself moved (normals turned, all else kept), with
another the moved samples; a PLY, PCD or LAS cloud is written so too, every point and field kept. Where one
cloud is ten or more times the size of the other, a warning asks whether both are in the same units (a
rigid motion cannot rescale). ``dit-register-series`` registers a whole series
of scans into one frame (see its ``--help``).

Every result carries a verdict from the model's own evidence: the target is registered onto the source as
well, and the result is trusted where the two motions agree closely (``--verdict fitness``: where enough of
the source lands on the target, one registration instead of two). A result not trusted is "unconfirmed"
where validation results that agreed as closely were mostly right (exit status 0, a one-line note on
stderr), else "probably wrong" (a one-line warning, exit status 3; ``--no-verdict-status`` keeps 0). Either
way it is printed and written. How often each level was right: docs/verdict.md. Scans (2,000 points or more
each) are registered by local features instead, both ways (``--features off`` runs the network): where
the two agree and no rival motion explains the features' matches as well, the result is trusted; otherwise
it is probably wrong.

The network handles rotations within its training range; --refine none is faster and less accurate, and
--any-rotation starts the network from 24 turns of SRC for clouds turned further, at several times the time
(measured ranges and times: docs/eval_modelnet40_unseen/angle_sweep.md and docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import os
import re
import sys
import warnings
from collections.abc import Callable

import numpy as np

from dit_jax import compile_cache, io, settings

PROG = "dit-register"
DEFAULT_MAX_POINTS = 5_000_000  # 120 MB of float64 coordinates per cloud; far more than sampling needs
#: Exit status when the verdict finds the result probably wrong.
EXIT_SUSPECT = 3
#: --refine's choices: :data:`dit_jax.settings.REFINEMENTS`, spelt out so that parsing imports no JAX.


def _add_reading_flags(parser: argparse.ArgumentParser) -> None:
    """How the clouds are read: the size read whole, and what happens to larger clouds and to non-finite points."""
    parser.add_argument(
        "--max-points",
        type=int,
        default=DEFAULT_MAX_POINTS,
        help=f"largest cloud read whole (default {DEFAULT_MAX_POINTS:,})",
    )
    parser.add_argument(
        "--no-downsample",
        action="store_true",
        help="refuse clouds above --max-points instead of reading a random subset",
    )
    parser.add_argument(
        "--drop-nonfinite",
        action="store_true",
        help="leave out points with NaN or Inf coordinates (depth cameras' and organized PCD "
        "files' pixels without a return) instead of refusing the file",
    )


def _add_checkpoint_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="orbax checkpoint directory or the authors' .pth (default: the shipped weights)",
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="formats: .ply (ascii/binary), .pcd (ascii/binary/binary_compressed), "
        ".npy, text (.xyz .txt .csv .asc .pts),\n"
        ".las and .laz (read; written only as SRC moved); "
        "meshes (.obj .off .stl, .ply with faces) "
        f"as {io.MESH_POINTS:,} points sampled over their surface\n\n"
        "exit status: 0 a result (trusted or unconfirmed); 2 bad input, nothing written; 3 a result that is\n"
        "probably wrong (printed and written all the same). A list (--pairs) ends with 2 where a pair of it has no\n"
        "result, else 3 where one is probably wrong, the pairs a resumed run skipped included.\n\n"
        + __doc__.split("\n\n")[-1].strip(),
    )
    parser.add_argument("src", nargs="?", help="the cloud (or mesh) to move")
    parser.add_argument("tgt", nargs="?", help="the cloud (or mesh) to align it to")
    parser.add_argument(
        "--pairs",
        default=None,
        metavar="LIST",
        help="instead of SRC TGT: a text file of pairs, 'SRC TGT' a line (paths relative to the "
        "list's folder, # comments), registered in this process, one JSON line per pair",
    )
    _add_results_flags(
        parser,
        "with --pairs: append each pair's JSON line here instead of printing it. The file is a log: "
        "nothing in it is ever cut or rewritten. Pairs it already holds a result for (same files, same "
        "settings) are skipped and errors are tried again, so a stopped run resumes; processes sharing the "
        "file (shards, or the same list twice) never register one pair twice",
    )
    parser.add_argument(
        "--shard",
        default=None,
        metavar="I/N",
        help="with --pairs: register only pairs I, I+N, I+2N, ... of the list (0 <= I < N), so N "
        "processes or array jobs share it",
    )
    parser.add_argument("--no-progress", action="store_true", help="with --pairs: no progress bar")
    _add_checkpoint_flag(parser)
    parser.add_argument(
        "--out",
        default=None,
        help="write SRC moved onto TGT here (format by extension; with SRC's own extension, a "
        "mesh or a PLY, PCD or LAS SRC is written whole: every point, face and field kept)",
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    settings.add_flags(parser)
    _add_reading_flags(parser)
    parser.add_argument(
        "--plot",
        default=None,
        metavar="FILE.png|FILE.html",
        help="draw both clouds before and after the registration, from two viewpoints (.png), or write one page "
        "a browser turns (.html)",
    )
    parser.add_argument(
        "--no-verdict-status",
        action="store_true",
        help=f"exit 0 even when the verdict finds the result probably wrong (else {EXIT_SUSPECT})",
    )
    compile_cache.add_arguments(parser)
    return parser


def _add_results_flags(parser: argparse.ArgumentParser, results_help: str) -> None:
    """``--results`` (``results_help``: what the command writes there) and ``--reuse-results``."""
    parser.add_argument("--results", default=None, metavar="FILE.jsonl", help=results_help)
    parser.add_argument(
        "--reuse-results",
        action="store_true",
        help="with --results: the file may hold records of other scans or other settings; keep them and "
        "add this run's beside them (else such a file is refused)",
    )


def _fail(message: str, prog: str = PROG) -> int:
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr)
    return 2


def _read(path: str, args, prog: str = PROG) -> np.ndarray:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", io.NonFiniteWarning)
        points, total = io.read(
            path, max_points=args.max_points, seed=args.seed or 0, return_count=True, drop_nonfinite=args.drop_nonfinite
        )
    for warning in caught:
        if issubclass(warning.category, io.NonFiniteWarning):
            print(f"{prog}: note: {warning.message}", file=sys.stderr)
        else:
            warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
    if total > len(points):
        if args.no_downsample:
            raise io.CloudFileError(
                path,
                f"{total:,} points, above the limit of {args.max_points:,} "
                f"(--max-points); drop --no-downsample to use a random subset",
            )
        print(
            f"{prog}: note: {path}: {total:,} points, above --max-points; using a random {len(points):,}",
            file=sys.stderr,
        )
    return points


def _output_problem(path: str | None, source: str | None = None, inputs: tuple = ()) -> str | None:
    """What is wrong with an --out path (a format not written, a folder, a missing or read-only folder, one of
    the ``inputs``), or None. A mesh or LAS file is written only as ``source`` moved, which must have that
    format."""
    if path is None:
        return None
    ext = os.path.splitext(path)[1].lower()
    if ext in io.MOVE_FORMATS and ext not in io.WRITE_FORMATS:
        if source is None or os.path.splitext(source)[1].lower() != ext:
            return (
                f"{path}: a {ext} file is written only as SRC moved, where SRC is a {ext} file; "
                f"choose one of {', '.join(io.WRITE_FORMATS)} for the moved points"
            )
    else:
        try:
            io.file_format(path, kind="output format", formats=io.WRITE_FORMATS)
        except io.CloudFileError as err:
            return str(err)
    return _writable_problem(path, inputs)


def _writable_problem(path: str, inputs: tuple = ()) -> str | None:
    """What keeps ``path`` from being written safely: a folder of that name, a missing or read-only folder, or
    the file being one of ``inputs`` (links included): an output never replaces an input."""
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        return f"{path}: is a folder; give a file name"
    if not os.path.isdir(folder):
        return f"{path}: its folder does not exist"
    if not os.access(folder, os.W_OK):
        return f"{path}: its folder is not writable"
    for given in inputs:
        if given is not None and os.path.exists(path) and os.path.exists(given) and os.path.samefile(path, given):
            return f"{path}: is the input {given}; an output never replaces an input, choose another name"
    return None


def _plot_problem(path: str | None, inputs: tuple = (), suffixes: tuple[str, ...] = (".png", ".html")) -> str | None:
    """What is wrong with a --plot path (not one of ``suffixes``, see :func:`_writable_problem`), or None."""
    if path is None:
        return None
    if not path.lower().endswith(suffixes):
        return f"--plot {path}: expected a {' or '.join(suffixes)} file name"
    return _writable_problem(path, inputs)


def _warning_lines(caught: list[warnings.WarningMessage], src: str, tgt: str) -> list[str]:
    """A registration's size-mismatch warnings as lines naming the files (``src``, ``tgt``) instead of "source"
    and "target"; any other warning is shown as Python shows it."""
    from dit_jax.sampling import SizeMismatchWarning

    lines = []
    for warning in caught:
        if issubclass(warning.category, SizeMismatchWarning):
            lines.append(
                str(warning.message)
                .replace("source", "\0", 1)
                .replace("target", "\1", 1)
                .replace("\0", src)
                .replace("\1", tgt)
            )
        else:
            warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
    return lines


def _write_moved(src: str, out: str, rotation: np.ndarray, translation: np.ndarray, points: np.ndarray) -> None:
    """Writes SRC moved to ``out``: the file itself (every point and field kept, :func:`io.move_file`) where
    both have the same one of :data:`io.MOVE_FORMATS`, else ``points`` (N, 3), what was read of it."""
    ext = os.path.splitext(out)[1].lower()
    if ext in io.MOVE_FORMATS and os.path.splitext(src)[1].lower() == ext:
        io.move_file(src, out, rotation, translation)
    else:
        io.write(out, points @ np.asarray(rotation).T + np.asarray(translation))


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


def _shard(text: str | None) -> tuple[int, int]:
    if text is None:
        return 0, 1
    match = re.fullmatch(r"(\d+)/(\d+)", text.strip())
    if not match or not int(match.group(1)) < int(match.group(2)):
        raise ValueError(f"--shard {text}: expected I/N with 0 <= I < N, such as 0/4")
    return int(match.group(1)), int(match.group(2))


def _reading(args) -> dict:
    """How the files were read: part of what makes two runs' results comparable."""
    return {"max_points": args.max_points, "drop_nonfinite": args.drop_nonfinite, "no_downsample": args.no_downsample}


def _open_results(args, pairs: list[tuple[str, str]], key: dict, prog: str = PROG):
    """The --results log, read and checked (:mod:`dit_jax.results_log`), or None without --results. Raises
    ValueError where it holds records of pairs other than ``pairs`` or other settings and --reuse-results was
    not given."""
    from dit_jax import results_log

    if args.results is None:
        return None
    if os.path.isdir(args.results):
        raise ValueError(f"--results {args.results}: is a folder; give a file name")
    log = results_log.ResultsFile(args.results)
    log.read_new()
    if log.bad_lines:
        shown = ", ".join(map(str, log.bad_lines[:10])) + (", ..." if len(log.bad_lines) > 10 else "")
        print(
            f"{prog}: note: {args.results}: {len(log.bad_lines)} line(s) do not parse and are skipped (left as "
            f"they are): line {shown}",
            file=sys.stderr,
        )
    if log.cut_short:
        print(f"{prog}: note: {args.results}: its last line is cut short; left as it is", file=sys.stderr)
    listed = {(os.path.abspath(src), os.path.abspath(tgt)) for src, tgt in pairs}

    def paths(record: dict) -> tuple:
        pair = record.get("pair")
        return (pair.get("src"), pair.get("tgt")) if isinstance(pair, dict) else ()

    foreign = [r for r in log.records if r.get("settings") != key or paths(r) not in listed]
    if foreign and not args.reuse_results:
        log.close()
        raise ValueError(
            f"--results {args.results}: holds {len(foreign)} record(s) of other pairs or other settings; "
            "give another file, or --reuse-results to add this run's records beside them"
        )
    return log


def _register_pair(model, args, src_path: str, tgt_path: str) -> dict:
    """One pair of the list registered: the result's JSON fields (and its warnings), or ``{"error": ...}``."""
    from dit_jax import sampling

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", sampling.SizeMismatchWarning)
            result = model.register(_read(src_path, args), _read(tgt_path, args))
    except sampling.InputError as err:  # name the files, not "source"/"target"
        message = str(err).replace("source:", f"{src_path}:", 1).replace("target:", f"{tgt_path}:", 1)
        return {"error": " ".join(message.split())}
    except (io.CloudFileError, ValueError, OSError) as err:
        return {"error": " ".join(str(err).split())}
    record = result.to_json()
    if problems := _warning_lines(caught, src_path, tgt_path):  # kept with the pair, not on stderr
        record["warnings"] = problems
    return record


def _register_list(args, pairs: list[tuple[str, str]], shard: tuple[int, int], model_kwargs: dict) -> int:
    """``--pairs``: the ``pairs`` of shard (index, count) through one loaded model; returns the exit status.

    With --results, a pair whose identity and settings already have a finished record is skipped; each pair
    is worked on under its lock, so processes sharing the file never register one pair twice."""
    from tqdm.auto import tqdm

    from dit_jax import registration, results_log

    index, count = shard
    chosen = [(k, pair) for k, pair in enumerate(pairs) if k % count == index]
    key = results_log.settings_key(args.checkpoint, model_kwargs, _reading(args))
    identities = {k: results_log.identity(*pair) for k, pair in chosen}
    log = _open_results(args, pairs, key)
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
        record |= _register_pair(model, args, src_path, tgt_path)
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
    return _list_status(args, [latest.get(k, {}) for k in identities])


def _list_status(args, records: list[dict]) -> int:
    """The exit status of a list from each chosen pair's newest record: 2 where one has no result, else 3
    where one is probably wrong (0 with --no-verdict-status), else 0."""
    errors = sum(not r or "error" in r for r in records)
    wrong = sum(r.get("level") == "probably wrong" for r in records)
    if errors:
        print(
            f"{PROG}: error: {errors} of {len(records)} pairs could not be registered (their lines say why)",
            file=sys.stderr,
        )
        return 2
    if wrong:
        print(f"{PROG}: warning: {wrong} of {len(records)} results are probably wrong", file=sys.stderr)
        return 0 if args.no_verdict_status else EXIT_SUSPECT
    return 0


def _model_kwargs(args) -> dict:
    """The inference settings the flags change."""
    return settings.changes(args)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)

    if args.pairs is not None:
        extra = [
            name
            for name, value in (("SRC TGT", args.src), ("--out", args.out), ("--plot", args.plot))
            if value is not None
        ]
        if extra:
            return _fail(f"--pairs registers a list; it cannot go with {', '.join(extra)}")
        try:  # the list and the shard are checked before any work
            pairs, shard = read_pair_list(args.pairs), _shard(args.shard)
        except (ValueError, OSError) as err:
            return _fail(str(err))
    elif args.src is None or args.tgt is None:
        return _fail("give SRC and TGT, or --pairs LIST")
    elif args.results is not None or args.shard is not None or args.reuse_results:
        return _fail("--results, --reuse-results and --shard go with --pairs")

    # Checked before any work, so a bad --out or --plot costs nothing and never replaces an input.
    problem = _output_problem(args.out, args.src, (args.src, args.tgt)) or _plot_problem(
        args.plot, (args.src, args.tgt)
    )
    if problem:
        return _fail(problem)
    if args.max_points < 1:
        return _fail(f"--max-points must be positive, got {args.max_points}")
    if args.max_disagreement is not None:
        if not 0.0 <= args.max_disagreement <= 180.0:
            return _fail(f"--max-disagreement must be between 0 and 180 degrees, got {args.max_disagreement:g}")
        if args.verdict == "fitness":
            return _fail(
                "--max-disagreement sets the agreement verdict's threshold; it cannot go with --verdict fitness"
            )

    if args.pairs is None:
        # The files first: bad input is reported before JAX is imported or a model loaded.
        try:
            src = _read(args.src, args)
            tgt = _read(args.tgt, args)
        except (io.CloudFileError, ValueError, OSError) as err:
            return _fail(str(err))

    compile_cache.from_args(args)
    from dit_jax import registration, sampling

    if args.pairs is not None:
        try:
            return _register_list(args, pairs, shard, _model_kwargs(args))
        except (ValueError, OSError) as err:  # a bad checkpoint or .pth file is a ValueError
            return _fail(str(err))
    try:
        model = registration.load(args.checkpoint, **_model_kwargs(args))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", sampling.SizeMismatchWarning)
                result = model.register(src, tgt)
        except sampling.InputError as err:  # name the files, not "source"/"target"
            message = str(err).replace("source:", f"{args.src}:", 1).replace("target:", f"{args.tgt}:", 1)
            return _fail(message)
        for line in _warning_lines(caught, args.src, args.tgt):
            print(f"{PROG}: warning: {line}", file=sys.stderr)
        if args.out is not None:
            _write_moved(args.src, args.out, result.rotation, result.translation, src)
        if args.plot is not None:
            result.plot(args.plot, src, tgt, title=f"{os.path.basename(args.src)} onto {os.path.basename(args.tgt)}")
    except (io.CloudFileError, ValueError, OSError) as err:  # bad checkpoints too
        return _fail(str(err))

    _print_result(result, args, len(src))
    if result.level == "unconfirmed":
        print(f"{PROG}: note: the result is not confirmed: {result.evidence()}", file=sys.stderr)
    elif result.level == "probably wrong":
        print(f"{PROG}: warning: the result is probably wrong: {result.evidence()}", file=sys.stderr)
        return 0 if args.no_verdict_status else EXIT_SUSPECT
    return 0


def _print_result(result, args: argparse.Namespace, n_source: int) -> None:
    """dit-register's report of one pair on stdout: its JSON with ``--json``, else the matrix, the motion, the
    verdict and the timings (``n_source``: the source points read)."""
    from dit_jax.geometry import rotation_angle_deg

    if args.json:
        report = result.to_json() | {"src": args.src, "tgt": args.tgt, "out": args.out, "plot": args.plot}
        print(json.dumps(report, indent=2))
    else:
        with np.printoptions(precision=9, suppress=True, floatmode="fixed", linewidth=120):
            print(result.matrix)
        angle = rotation_angle_deg(result.rotation)
        print(f"rotation {angle:.3f} deg, translation {np.linalg.norm(result.translation):.6g} (units of the input)")
        print(f"{result.level}: {result.evidence()}")
        print(
            f"fitness {result.fitness:.3f}, inlier ratio {result.inlier_ratio:.3f}, "
            f"{len(result.source_indices)} of {n_source} source points used, {result.seconds:.2f} s"
            + (f" + {result.refine_seconds:.2f} s of {result.refinement.upper()}" if result.refinement else "")
            + (f" + {result.candidate_seconds:.2f} s of feature matching" if result.candidate_seconds else "")
        )
        print(f"found by: {result.label}")
        if args.any_rotation:
            print(f"rotation search: went on from a start turned {result.start_turn:.0f} deg")
        for written in (args.out, args.plot):
            if written is not None:
                print(f"wrote {written}")


SERIES_PROG = "dit-register-series"


def _series_parser() -> argparse.ArgumentParser:
    parser = _many_scans_parser(
        SERIES_PROG,
        "Register a series of scans, each onto the one before, and print every scan's pose in the first one's "
        "frame (dit_jax.series).",
        "Prints each scan's 4x4 pose (x_first = R x_scan + t) and each link's verdict. With --loop the "
        "last scan is registered onto the first too and the loop's gap (the motion left after going "
        "once around it) is spread over the links. Exit status 3 where a link is probably wrong or the loop's "
        f"gap exceeds {LOOP_GAP_WARNING_DEG:g} degrees (a link is then most likely wrong); 2 on bad input.",
        "the scans (or meshes) in the order they were taken, at least 2",
    )
    parser.add_argument(
        "--loop", action="store_true", help="the last scan overlaps the first (a full turn): close the loop"
    )
    parser.add_argument("--out", default=None, help="write every scan moved into the first one's frame, as one cloud")
    parser.add_argument(
        "--out-dir",
        default=None,
        metavar="DIR",
        help="write each scan moved into the first one's frame to DIR, under its own name and "
        "format (PLY, PCD, LAS and meshes whole: every point and field kept)",
    )
    _add_many_scans_flags(
        parser,
        plot=(
            "FILE.png",
            "draw every scan in the first one's frame, from two sides, beside each link's agreement and verdict",
        ),
        shows="poses, links and the loop's gap",
        suspect="when a link is probably wrong or the loop's gap is large",
    )
    return parser


def _many_scans_parser(prog: str, description: str, epilog: str, scans: str) -> argparse.ArgumentParser:
    """A parser of dit-register-series or dit-register-scene: the scans (``scans``: their help) and the weights."""
    parser = argparse.ArgumentParser(
        prog=prog, formatter_class=argparse.RawDescriptionHelpFormatter, description=description, epilog=epilog
    )
    parser.add_argument("scans", nargs="+", help=scans)
    _add_checkpoint_flag(parser)
    return parser


def _add_many_scans_flags(parser: argparse.ArgumentParser, *, plot: tuple[str, str], shows: str, suspect: str) -> None:
    """The flags dit-register-series and dit-register-scene share: ``--plot`` (``plot``: its file name and help),
    ``--json`` (printing what ``shows`` says), the settings they take, reading, progress, the exit status
    (``suspect``: when it would be 3) and the compilation cache."""
    parser.add_argument("--plot", default=None, metavar=plot[0], help=plot[1])
    parser.add_argument("--json", action="store_true", help=f"print {shows} as JSON")
    settings.add_flags(parser, ("refine", "viewpoint", "descriptor", "seed"))
    _add_reading_flags(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-verdict-status", action="store_true", help=f"exit 0 even {suspect} (else {EXIT_SUSPECT})")
    compile_cache.add_arguments(parser)


def _out_dir_problem(folder: str | None, scans: list[str]) -> str | None:
    """What is wrong with --out-dir (its parent missing, two scans of one name, a scan it would overwrite)."""
    if folder is None:
        return None
    if not os.path.isdir(os.path.dirname(os.path.abspath(folder))):
        return f"--out-dir {folder}: its parent folder does not exist"
    names = [os.path.basename(path) for path in scans]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        return f"--out-dir {folder}: two scans are named {twice[0]}; one would overwrite the other there"
    for path in scans:
        if os.path.realpath(os.path.dirname(os.path.abspath(path))) == os.path.realpath(folder):
            return f"--out-dir {folder}: it holds {path}, which the moved scan would overwrite"
    return None


#: ``dit-register-series`` warns where the loop's rotation gap exceeds this many degrees: the links' own errors
#: (a few tenths of a degree each on the dragon's scans) sum to far less.
LOOP_GAP_WARNING_DEG = 5.0


def series_main(argv: list[str] | None = None) -> int:
    """``dit-register-series SCAN SCAN [SCAN ...] [--loop]``: see :func:`_series_parser`."""
    args = _series_parser().parse_args(argv)
    fail = lambda message: _fail(message, SERIES_PROG)  # noqa: E731
    if len(args.scans) < (3 if args.loop else 2):
        return fail(
            f"{'--loop needs at least 3 scans' if args.loop else 'a series needs at least 2 scans'}, "
            f"got {len(args.scans)}"
        )
    scans = tuple(args.scans)
    problem = (
        _output_problem(args.out, inputs=scans)
        or _out_dir_problem(args.out_dir, args.scans)
        or _plot_problem(args.plot, scans, (".png",))
    )
    if problem:
        return fail(problem)
    if args.max_points < 1:
        return fail(f"--max-points must be positive, got {args.max_points}")
    compile_cache.from_args(args)
    from tqdm import tqdm

    from dit_jax import registration, sampling, series

    try:
        clouds = [_read(path, args, SERIES_PROG) for path in args.scans]
        model = registration.load(args.checkpoint, **settings.changes(args))
        pairs = series.link_pairs(len(clouds), args.loop)
        with (
            tqdm(
                total=len(pairs),
                desc="links",
                unit="link",
                file=sys.stderr,
                disable=args.no_progress or not sys.stderr.isatty(),
            ) as bar,
            warnings.catch_warnings(record=True) as caught,
        ):
            warnings.simplefilter("always", sampling.SizeMismatchWarning)

            def link_done(done: int, total: int) -> None:  # each link's warnings name its two scans
                bar.update(1)
                a, b = pairs[done - 1]
                for line in _warning_lines(caught, args.scans[a], args.scans[b]):
                    bar.write(f"{SERIES_PROG}: warning: {line}", file=sys.stderr)
                caught.clear()

            try:
                result = series.register_series(model, clouds, loop=args.loop, progress=link_done)
            except sampling.InputError as err:
                return fail(str(err))
        _write_series(result, args, clouds)
    except (io.CloudFileError, ValueError, OSError) as err:  # bad checkpoints too
        return fail(str(err))

    names = args.scans
    _print_series(result, args, pairs)
    for (a, b), link in zip(pairs, result.links):
        if link.level == "unconfirmed":
            print(
                f"{SERIES_PROG}: note: {names[a]} onto {names[b]} is not confirmed: {link.evidence()}", file=sys.stderr
            )
    problems = [
        f"{names[a]} onto {names[b]} is probably wrong"
        for (a, b), link in zip(pairs, result.links)
        if link.level == "probably wrong"
    ]
    if args.loop and result.loop_gap_deg > LOOP_GAP_WARNING_DEG:
        problems.append(
            f"the loop's gap is {result.loop_gap_deg:.1f} deg, above {LOOP_GAP_WARNING_DEG:g}: "
            f"a link is most likely wrong"
        )
    for problem in problems:
        print(f"{SERIES_PROG}: warning: {problem}", file=sys.stderr)
    return EXIT_SUSPECT if problems and not args.no_verdict_status else 0


def _write_series(result, args: argparse.Namespace, clouds: list[np.ndarray]) -> None:
    """dit-register-series's files: the merged cloud (``--out``), the picture (``--plot``) and each scan moved
    into the first one's frame (``--out-dir``)."""
    if args.out is not None:
        io.write(args.out, result.merged(clouds))
    if args.plot is not None:
        result.plot(args.plot, clouds, names=[os.path.basename(path) for path in args.scans])
    if args.out_dir is not None:
        os.makedirs(args.out_dir, exist_ok=True)
        for path, pose, cloud in zip(args.scans, result.poses, clouds):
            _write_moved(path, os.path.join(args.out_dir, os.path.basename(path)), pose[:3, :3], pose[:3, 3], cloud)


def _print_series(result, args: argparse.Namespace, pairs: list[tuple[int, int]]) -> None:
    """dit-register-series's report on stdout: its JSON with ``--json``, else each scan's pose, each link's verdict
    (``pairs``: the scans each link joins), the loop's gap and the files written."""
    from dit_jax.geometry import rotation_angle_deg

    names = args.scans
    if args.json:
        report = {
            "scans": names,
            "poses": result.poses.tolist(),
            "out": args.out,
            "out_dir": args.out_dir,
            "plot": args.plot,
            "links": [
                {"source": names[a], "target": names[b]} | link.to_json() for (a, b), link in zip(pairs, result.links)
            ],
            "loop_gap_deg": None if np.isnan(result.loop_gap_deg) else result.loop_gap_deg,
            "loop_gap": None if np.isnan(result.loop_gap) else result.loop_gap,
        }
        print(json.dumps(report, indent=2))
    else:
        with np.printoptions(precision=9, suppress=True, floatmode="fixed", linewidth=120):
            for name, pose in zip(names, result.poses):
                print(
                    f"{name}: rotation {rotation_angle_deg(pose[:3, :3]):.3f} deg, translation "
                    f"{np.linalg.norm(pose[:3, 3]):.6g} from {names[0]}'s frame"
                )
                print(pose)
        for (a, b), link in zip(pairs, result.links):
            print(f"{names[a]} onto {names[b]}: {link.level}: {link.evidence()}")
        if args.loop:
            print(
                f"loop: gap {result.loop_gap_deg:.3f} deg and {result.loop_gap:.6g} (units of the input) "
                f"before closing, spread over {len(pairs)} links"
            )
        if args.out is not None:
            print(f"wrote {args.out}")
        if args.out_dir is not None:
            print(f"wrote {len(args.scans)} moved scans to {args.out_dir}")
        if args.plot is not None:
            print(f"wrote {args.plot}")


SCENE_PROG = "dit-register-scene"
#: dit-register-scene's pose files, by flag: the form :func:`dit_jax.scene.pose_lines` writes.
POSE_FORMS = {"kitti": "kitti", "tum": "tum"}


def _scene_parser() -> argparse.ArgumentParser:
    parser = _many_scans_parser(
        SCENE_PROG,
        "Register the scans of one scene (fragments of a room, views of an object) into one frame by a pose "
        "graph over their pairwise registrations (dit_jax.scene).",
        "Registers each scan onto its neighbours in the list, then the pairs the first placement lays over each "
        "other; trusted results are the graph's edges (unconfirmed ones uncertain edges, probably wrong ones "
        "none), and the scans' poses are optimised over them, the uncertain edges that disagree with the rest "
        "switched off. The largest group of scans the edges join is the scene, in its first scan's frame; "
        "other groups are reported and left out. Prints each scan's pose (x_frame = R x_scan + t) and the "
        "edges. Exit status 3 where a scan is left out; 2 on bad input.",
        "the scans (or meshes) of the scene, at least 2",
    )
    parser.add_argument("--out", default=None, help="write the scene's scans in its frame, as one cloud")
    parser.add_argument(
        "--voxel", type=float, default=None, metavar="SIZE", help="--out keeps one point per cell of this size"
    )
    parser.add_argument("--poses", default=None, metavar="FILE.json", help="write poses, edges and components as JSON")
    _add_results_flags(
        parser,
        "append each registered pair's JSON line here (the result in full). The file is a log: nothing in it is "
        "ever cut or rewritten. Pairs it already holds (same files, same settings) are taken from it, so a "
        "stopped run resumes where it stopped and builds the same scene",
    )
    for form in POSE_FORMS:
        parser.add_argument(
            f"--{form}",
            default=None,
            metavar="FILE.txt",
            help=f"write the placed scans' poses in {form.upper()}'s text form",
        )
    _add_many_scans_flags(
        parser,
        plot=(
            "FILE.html",
            "write one page a browser turns: the scene's scans in its frame, each in its colour, and the edges "
            "(FILE.png: a picture of them from two sides)",
        ),
        shows="the scene",
        suspect="where a scan joins nothing",
    )
    return parser


def _text_output_problem(path: str | None, flag: str, inputs: tuple) -> str | None:
    """What is wrong with a text output's path (its folder missing, one of the ``inputs``), or None."""
    if path is None:
        return None
    if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        return f"{flag} {path}: its folder does not exist"
    if any(os.path.realpath(path) == os.path.realpath(p) for p in inputs):
        return f"{flag} {path}: it is one of the scans"
    return None


def scene_main(argv: list[str] | None = None) -> int:
    """``dit-register-scene SCAN SCAN [SCAN ...]``: see :func:`_scene_parser`."""
    args = _scene_parser().parse_args(argv)
    fail = lambda message: _fail(message, SCENE_PROG)  # noqa: E731
    if len(args.scans) < 2:
        return fail(f"a scene needs at least 2 scans, got {len(args.scans)}")
    scans = tuple(args.scans)
    texts = [(args.poses, "--poses"), (args.results, "--results")]
    texts += [(getattr(args, form), f"--{form}") for form in POSE_FORMS]
    problem = (
        _output_problem(args.out, inputs=scans)
        or next((p for p in (_text_output_problem(path, flag, scans) for path, flag in texts) if p), None)
        or _plot_problem(args.plot, scans, (".html", ".png"))
    )
    if args.voxel is not None and not args.voxel > 0:
        problem = problem or f"--voxel must be positive, got {args.voxel}"
    if args.reuse_results and args.results is None:
        problem = problem or "--reuse-results goes with --results"
    if problem:
        return fail(problem)
    compile_cache.from_args(args)
    from tqdm import tqdm

    from dit_jax import registration, sampling, scene

    try:
        clouds = [_read(path, args, SCENE_PROG) for path in scans]
        model = registration.load(args.checkpoint, **settings.changes(args))
        bar = tqdm(
            total=0, desc="pairs", unit="pair", file=sys.stderr, disable=args.no_progress or not sys.stderr.isatty()
        )
        log, known, on_result = _scene_results(args, scans)
        with bar, warnings.catch_warnings(), log or contextlib.nullcontext():
            warnings.simplefilter("ignore", sampling.SizeMismatchWarning)  # a scene's scans differ in extent
            built = scene.register_scene(model, clouds, known=known, on_result=on_result, **scene.progress(bar))
        _write_scene(built, args, clouds)
    except sampling.InputError as err:
        return fail(str(err))
    except (io.CloudFileError, ValueError, OSError) as err:  # bad checkpoints too
        return fail(str(err))
    _print_scene(built, args)
    left_out = [scans[k] for k in range(len(scans)) if not built.placed[k]]
    for name in left_out:
        print(f"{SCENE_PROG}: warning: {name} joins no scan of the scene: left out", file=sys.stderr)
    if len(built.components) > 1:
        groups = ", ".join(str(len(c)) for c in built.components)
        print(
            f"{SCENE_PROG}: warning: the scans form {len(built.components)} groups ({groups} scans); the scene is the first",
            file=sys.stderr,
        )
    return EXIT_SUSPECT if left_out and not args.no_verdict_status else 0


def _scene_results(args: argparse.Namespace, scans: tuple[str, ...]) -> tuple:
    """``--results`` of dit-register-scene: ``(log, known, on_result)`` for :func:`dit_jax.scene.register_scene`,
    the pairs of these scans the log holds under this run's settings, and the callback that appends each new
    one; ``(None, None, None)`` without --results."""
    from dit_jax import results_log
    from dit_jax.result import Result

    key = {**results_log.settings_key(args.checkpoint, settings.changes(args), _reading(args)), "job": "scene"}
    pairs = [(s, t) for s in scans for t in scans if s != t]
    log = _open_results(args, pairs, key, SCENE_PROG)
    if log is None:
        return None, None, None
    by_identity: dict[str, list[tuple[int, int]]] = {}
    for s, t in itertools.permutations(range(len(scans)), 2):
        by_identity.setdefault(results_log.identity_key(results_log.identity(scans[s], scans[t])), []).append((s, t))
    known = {}
    for record in log.records:
        if record.get("settings") != key or not isinstance(record.get("result"), dict):
            continue
        try:
            result = Result.from_record(record["result"])
        except ValueError:
            continue  # a record this version cannot read back: its pair is registered again
        for pair in by_identity.get(results_log.identity_key(record.get("pair")), ()):
            known[pair] = result

    def append(pair: tuple[int, int], result: Result) -> None:
        src, tgt = scans[pair[0]], scans[pair[1]]
        record = {"src": src, "tgt": tgt, "pair": results_log.identity(src, tgt), "settings": key}
        log.append(record | result.to_json() | {"result": result.to_record()})

    return log, known, append


def _write_scene(built, args: argparse.Namespace, clouds: list[np.ndarray]) -> None:
    from dit_jax import scene

    if args.out is not None:
        io.write(args.out, built.merged(clouds, args.voxel))
    if args.poses is not None:
        io.write_text(args.poses, json.dumps(built.to_json(args.scans), indent=2) + "\n")
    for form in POSE_FORMS:
        if getattr(args, form) is not None:
            io.write_text(getattr(args, form), scene.pose_lines(built.poses, built.placed, POSE_FORMS[form]))
    if args.plot is not None:
        built.plot(args.plot, clouds, [os.path.basename(path) for path in args.scans])


def _print_scene(built, args: argparse.Namespace) -> None:
    """dit-register-scene's report on stdout: the scene as JSON with ``--json``, else each scan's pose, the
    edges' counts and the files written."""
    from dit_jax.geometry import rotation_angle_deg

    names = args.scans
    if args.json:
        print(json.dumps(built.to_json(names), indent=2))
        return
    with np.printoptions(precision=9, suppress=True, floatmode="fixed", linewidth=120):
        for k, (name, pose, placed) in enumerate(zip(names, built.poses, built.placed)):
            if not placed:
                print(f"{name}: left out (in group {built.component_of(k) + 1} of {len(built.components)})")
                continue
            print(
                f"{name}: rotation {rotation_angle_deg(pose[:3, :3]):.3f} deg, translation "
                f"{np.linalg.norm(pose[:3, 3]):.6g} in {names[built.frame]}'s frame"
            )
            print(pose)
    kept = sum(e.kept for e in built.edges)
    print(
        f"edges: {len(built.edges) + len(built.rejected)} pairs registered, {kept} kept, "
        f"{len(built.edges) - kept} switched off by the optimisation, {len(built.rejected)} probably wrong"
    )
    for path in (args.out, args.poses, *(getattr(args, form) for form in POSE_FORMS), args.plot):
        if path is not None:
            print(f"wrote {path}")


def _console_script(command: Callable[[], int]) -> Callable[[], None]:
    """A console script's entry point: runs ``command``, flushes the output streams and ends the process
    without Python's shutdown, which tears JAX's runtime down for about a quarter of a second after every file
    is written and closed (docs/benchmarks.md, "Start-up"). An exception still ends it the usual way."""

    def run() -> None:
        status = command()
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):  # a closed pipe, a closed stream
                stream.flush()
        os._exit(status)

    return run


register_command = _console_script(main)
series_command = _console_script(series_main)
scene_command = _console_script(scene_main)


if __name__ == "__main__":
    register_command()
