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
import json
import os
import sys
import warnings

import numpy as np

from dit_jax import io
from dit_jax.cli import files, pair_list
from dit_jax.network import compile_cache
from dit_jax.pipeline import settings


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=files.PROG,
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
    files.add_results_flags(
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
    files.add_checkpoint_flag(parser)
    parser.add_argument(
        "--out",
        default=None,
        help="write SRC moved onto TGT here (format by extension; with SRC's own extension, a "
        "mesh or a PLY, PCD or LAS SRC is written whole: every point, face and field kept)",
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    settings.add_flags(parser)
    files.add_reading_flags(parser)
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
        help=f"exit 0 even when the verdict finds the result probably wrong (else {files.EXIT_SUSPECT})",
    )
    compile_cache.add_arguments(parser)
    return parser


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
            return files.fail(f"--pairs registers a list; it cannot go with {', '.join(extra)}")
        try:  # the list and the shard are checked before any work
            pairs, shard = pair_list.read_pair_list(args.pairs), pair_list.shard(args.shard)
        except (ValueError, OSError) as err:
            return files.fail(str(err))
    elif args.src is None or args.tgt is None:
        return files.fail("give SRC and TGT, or --pairs LIST")
    elif args.results is not None or args.shard is not None or args.reuse_results:
        return files.fail("--results, --reuse-results and --shard go with --pairs")

    # Checked before any work, so a bad --out or --plot costs nothing and never replaces an input.
    problem = files.output_problem(args.out, args.src, (args.src, args.tgt)) or files.plot_problem(
        args.plot, (args.src, args.tgt)
    )
    if problem:
        return files.fail(problem)
    if args.max_points < 1:
        return files.fail(f"--max-points must be positive, got {args.max_points}")
    if args.max_disagreement is not None:
        if not 0.0 <= args.max_disagreement <= 180.0:
            return files.fail(f"--max-disagreement must be between 0 and 180 degrees, got {args.max_disagreement:g}")
        if args.verdict == "fitness":
            return files.fail(
                "--max-disagreement sets the agreement verdict's threshold; it cannot go with --verdict fitness"
            )

    if args.pairs is None:
        # The files first: bad input is reported before JAX is imported or a model loaded.
        try:
            src = files.read_cloud(args.src, args)
            tgt = files.read_cloud(args.tgt, args)
        except (io.CloudFileError, ValueError, OSError) as err:
            return files.fail(str(err))

    compile_cache.from_args(args)
    from dit_jax.pipeline import registration, sampling

    if args.pairs is not None:
        try:
            return pair_list.register_list(args, pairs, shard, _model_kwargs(args))
        except (ValueError, OSError) as err:  # a bad checkpoint or .pth file is a ValueError
            return files.fail(str(err))
    try:
        model = registration.load(args.checkpoint, **_model_kwargs(args))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", sampling.SizeMismatchWarning)
                result = model.register(src, tgt)
        except sampling.InputError as err:  # name the files, not "source"/"target"
            message = str(err).replace("source:", f"{args.src}:", 1).replace("target:", f"{args.tgt}:", 1)
            return files.fail(message)
        for line in files.warning_lines(caught, args.src, args.tgt):
            print(f"{files.PROG}: warning: {line}", file=sys.stderr)
        if args.out is not None:
            files.write_moved(args.src, args.out, result.rotation, result.translation, src)
        if args.plot is not None:
            result.plot(args.plot, src, tgt, title=f"{os.path.basename(args.src)} onto {os.path.basename(args.tgt)}")
    except (io.CloudFileError, ValueError, OSError) as err:  # bad checkpoints too
        return files.fail(str(err))

    _print_result(result, args, len(src))
    if result.level == "unconfirmed":
        print(f"{files.PROG}: note: the result is not confirmed: {result.evidence()}", file=sys.stderr)
    elif result.level == "probably wrong":
        print(f"{files.PROG}: warning: the result is probably wrong: {result.evidence()}", file=sys.stderr)
        return 0 if args.no_verdict_status else files.EXIT_SUSPECT
    return 0


def _print_result(result, args: argparse.Namespace, n_source: int) -> None:
    """dit-register's report of one pair on stdout: its JSON with ``--json``, else the matrix, the motion, the
    verdict and the timings (``n_source``: the source points read)."""
    from dit_jax.geometry.rigid import rotation_angle_deg

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


command = files.console_script(main)


if __name__ == "__main__":
    command()
