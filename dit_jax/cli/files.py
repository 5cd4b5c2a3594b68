"""What the commands share: the flags every one takes, reading clouds as they say, checking each output path
before any work (an output never replaces an input), and the console scripts' quick exit."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import warnings
from collections.abc import Callable

import numpy as np

from dit_jax import io
from dit_jax.network import compile_cache
from dit_jax.pipeline import settings

PROG = "dit-register"


DEFAULT_MAX_POINTS = 5_000_000  # 120 MB of float64 coordinates per cloud; far more than sampling needs


#: Exit status when the verdict finds the result probably wrong.
EXIT_SUSPECT = 3


def add_reading_flags(parser: argparse.ArgumentParser) -> None:
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


def add_checkpoint_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="orbax checkpoint directory or the authors' .pth (default: the shipped weights)",
    )


def add_results_flags(parser: argparse.ArgumentParser, results_help: str) -> None:
    """``--results`` (``results_help``: what the command writes there) and ``--reuse-results``."""
    parser.add_argument("--results", default=None, metavar="FILE.jsonl", help=results_help)
    parser.add_argument(
        "--reuse-results",
        action="store_true",
        help="with --results: the file may hold records of other scans or other settings; keep them and "
        "add this run's beside them (else such a file is refused)",
    )


def many_scans_parser(prog: str, description: str, epilog: str, scans: str) -> argparse.ArgumentParser:
    """A parser of dit-register-series or dit-register-scene: the scans (``scans``: their help) and the weights."""
    parser = argparse.ArgumentParser(
        prog=prog, formatter_class=argparse.RawDescriptionHelpFormatter, description=description, epilog=epilog
    )
    parser.add_argument("scans", nargs="+", help=scans)
    add_checkpoint_flag(parser)
    return parser


def add_many_scans_flags(parser: argparse.ArgumentParser, *, plot: tuple[str, str], shows: str, suspect: str) -> None:
    """The flags dit-register-series and dit-register-scene share: ``--plot`` (``plot``: its file name and help),
    ``--json`` (printing what ``shows`` says), the settings they take, reading, progress, the exit status
    (``suspect``: when it would be 3) and the compilation cache."""
    parser.add_argument("--plot", default=None, metavar=plot[0], help=plot[1])
    parser.add_argument("--json", action="store_true", help=f"print {shows} as JSON")
    settings.add_flags(parser, ("refine", "viewpoint", "descriptor", "seed"))
    add_reading_flags(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-verdict-status", action="store_true", help=f"exit 0 even {suspect} (else {EXIT_SUSPECT})")
    compile_cache.add_arguments(parser)


def fail(message: str, prog: str = PROG) -> int:
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr)
    return 2


def read_cloud(path: str, args, prog: str = PROG) -> np.ndarray:
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


def reading_key(args) -> dict:
    """How the files were read: part of what makes two runs' results comparable."""
    return {"max_points": args.max_points, "drop_nonfinite": args.drop_nonfinite, "no_downsample": args.no_downsample}


def warning_lines(caught: list[warnings.WarningMessage], src: str, tgt: str) -> list[str]:
    """A registration's size-mismatch warnings as lines naming the files (``src``, ``tgt``) instead of "source"
    and "target"; any other warning is shown as Python shows it."""
    from dit_jax.pipeline.sampling import SizeMismatchWarning

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


def output_problem(path: str | None, source: str | None = None, inputs: tuple = ()) -> str | None:
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
    return writable_problem(path, inputs)


def writable_problem(path: str, inputs: tuple = ()) -> str | None:
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


def plot_problem(path: str | None, inputs: tuple = (), suffixes: tuple[str, ...] = (".png", ".html")) -> str | None:
    """What is wrong with a --plot path (not one of ``suffixes``, see :func:`writable_problem`), or None."""
    if path is None:
        return None
    if not path.lower().endswith(suffixes):
        return f"--plot {path}: expected a {' or '.join(suffixes)} file name"
    return writable_problem(path, inputs)


def out_dir_problem(folder: str | None, scans: list[str]) -> str | None:
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


def text_output_problem(path: str | None, flag: str, inputs: tuple) -> str | None:
    """What is wrong with a text output's path (its folder missing, one of the ``inputs``), or None."""
    if path is None:
        return None
    if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        return f"{flag} {path}: its folder does not exist"
    if any(os.path.realpath(path) == os.path.realpath(p) for p in inputs):
        return f"{flag} {path}: it is one of the scans"
    return None


def write_moved(src: str, out: str, rotation: np.ndarray, translation: np.ndarray, points: np.ndarray) -> None:
    """Writes SRC moved to ``out``: the file itself (every point and field kept, :func:`io.move_file`) where
    both have the same one of :data:`io.MOVE_FORMATS`, else ``points`` (N, 3), what was read of it."""
    ext = os.path.splitext(out)[1].lower()
    if ext in io.MOVE_FORMATS and os.path.splitext(src)[1].lower() == ext:
        io.move_file(src, out, rotation, translation)
    else:
        io.write(out, points @ np.asarray(rotation).T + np.asarray(translation))


def console_script(command: Callable[[], int]) -> Callable[[], None]:
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


def open_results(args, pairs: list[tuple[str, str]], key: dict, prog: str = PROG):
    """The --results log, read and checked (:mod:`dit_jax.cli.results_log`), or None without --results. Raises
    ValueError where it holds records of pairs other than ``pairs`` or other settings and --reuse-results was
    not given."""
    from dit_jax.cli import results_log

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
