"""``dit-register-series SCAN SCAN [SCAN ...]``: a series of scans, each registered onto the one before, in the
first one's frame (:mod:`dit_jax.scenes.series`)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings

import numpy as np

from dit_jax import io
from dit_jax.cli import files
from dit_jax.network import compile_cache
from dit_jax.pipeline import settings

SERIES_PROG = "dit-register-series"


#: ``dit-register-series`` warns where the loop's rotation gap exceeds this many degrees: the links' own errors
#: (a few tenths of a degree each on the dragon's scans) sum to far less.
LOOP_GAP_WARNING_DEG = 5.0


def _parser() -> argparse.ArgumentParser:
    parser = files.many_scans_parser(
        SERIES_PROG,
        "Register a series of scans, each onto the one before, and print every scan's pose in the first one's "
        "frame (dit_jax.scenes.series).",
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
    files.add_many_scans_flags(
        parser,
        plot=(
            "FILE.png",
            "draw every scan in the first one's frame, from two sides, beside each link's agreement and verdict",
        ),
        shows="poses, links and the loop's gap",
        suspect="when a link is probably wrong or the loop's gap is large",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """``dit-register-series SCAN SCAN [SCAN ...] [--loop]``: see :func:`_parser`."""
    args = _parser().parse_args(argv)
    fail = lambda message: files.fail(message, SERIES_PROG)  # noqa: E731
    if len(args.scans) < (3 if args.loop else 2):
        return fail(
            f"{'--loop needs at least 3 scans' if args.loop else 'a series needs at least 2 scans'}, "
            f"got {len(args.scans)}"
        )
    scans = tuple(args.scans)
    problem = (
        files.output_problem(args.out, inputs=scans)
        or files.out_dir_problem(args.out_dir, args.scans)
        or files.plot_problem(args.plot, scans, (".png",))
    )
    if problem:
        return fail(problem)
    if args.max_points < 1:
        return fail(f"--max-points must be positive, got {args.max_points}")
    compile_cache.from_args(args)
    from tqdm import tqdm

    from dit_jax.pipeline import registration, sampling
    from dit_jax.scenes import series

    try:
        clouds = [files.read_cloud(path, args, SERIES_PROG) for path in args.scans]
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
                for line in files.warning_lines(caught, args.scans[a], args.scans[b]):
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
    return files.EXIT_SUSPECT if problems and not args.no_verdict_status else 0


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
            files.write_moved(
                path, os.path.join(args.out_dir, os.path.basename(path)), pose[:3, :3], pose[:3, 3], cloud
            )


def _print_series(result, args: argparse.Namespace, pairs: list[tuple[int, int]]) -> None:
    """dit-register-series's report on stdout: its JSON with ``--json``, else each scan's pose, each link's verdict
    (``pairs``: the scans each link joins), the loop's gap and the files written."""
    from dit_jax.geometry.rigid import rotation_angle_deg

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


command = files.console_script(main)


if __name__ == "__main__":
    command()
