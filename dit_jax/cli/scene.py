"""``dit-register-scene SCAN SCAN [SCAN ...]``: the scans of one scene placed by a pose graph over their
pairwise registrations (:mod:`dit_jax.scenes.scene`)."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import sys
import warnings

import numpy as np

from dit_jax import io
from dit_jax.cli import files
from dit_jax.network import compile_cache
from dit_jax.pipeline import settings

SCENE_PROG = "dit-register-scene"


#: dit-register-scene's pose files, by flag: the form :func:`dit_jax.scenes.scene.pose_lines` writes.
POSE_FORMS = {"kitti": "kitti", "tum": "tum"}


def _parser() -> argparse.ArgumentParser:
    parser = files.many_scans_parser(
        SCENE_PROG,
        "Register the scans of one scene (fragments of a room, views of an object) into one frame by a pose "
        "graph over their pairwise registrations (dit_jax.scenes.scene).",
        "Registers each scan onto its neighbours in the list, then the pairs the first placement lays over each "
        "other; trusted results are the graph's edges (unconfirmed ones uncertain edges, probably wrong ones "
        "none), and the scans' poses are optimised over them, the uncertain edges that disagree with the rest "
        "switched off. The largest group of scans the edges join is the scene, in its first scan's frame; "
        "other groups are reported and left out. Prints each scan's pose (x_frame = R x_scan + t) and the "
        "edges. Exit status 3 where a scan is left out; 2 on bad input.",
        "the scans (or meshes) of the scene, at least 2",
    )
    files.add_many_scans_flags(
        parser,
        plot=(
            "FILE.html",
            "write one page a browser turns: the scene's scans in its frame, each in its colour, and the edges "
            "(FILE.png: a picture of them from two sides)",
        ),
        shows="the scene",
        suspect="where a scan joins nothing",
    )
    parser.add_argument("--out", default=None, help="write the scene's scans in its frame, as one cloud")
    parser.add_argument(
        "--voxel", type=float, default=None, metavar="SIZE", help="--out keeps one point per cell of this size"
    )
    parser.add_argument("--poses", default=None, metavar="FILE.json", help="write poses, edges and components as JSON")
    files.add_results_flags(
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
    return parser


def main(argv: list[str] | None = None) -> int:
    """``dit-register-scene SCAN SCAN [SCAN ...]``: see :func:`_parser`."""
    args = _parser().parse_args(argv)
    fail = lambda message: files.fail(message, SCENE_PROG)  # noqa: E731
    if len(args.scans) < 2:
        return fail(f"a scene needs at least 2 scans, got {len(args.scans)}")
    scans = tuple(args.scans)
    texts = [(args.poses, "--poses"), (args.results, "--results")]
    texts += [(getattr(args, form), f"--{form}") for form in POSE_FORMS]
    problem = (
        files.output_problem(args.out, inputs=scans)
        or next((p for p in (files.text_output_problem(path, flag, scans) for path, flag in texts) if p), None)
        or files.plot_problem(args.plot, scans, (".html", ".png"))
    )
    if args.voxel is not None and not args.voxel > 0:
        problem = problem or f"--voxel must be positive, got {args.voxel}"
    if args.reuse_results and args.results is None:
        problem = problem or "--reuse-results goes with --results"
    if problem:
        return fail(problem)
    compile_cache.from_args(args)
    from tqdm import tqdm

    from dit_jax.pipeline import registration, sampling
    from dit_jax.scenes import scene

    try:
        clouds = [files.read_cloud(path, args, SCENE_PROG) for path in scans]
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
    return files.EXIT_SUSPECT if left_out and not args.no_verdict_status else 0


def _scene_results(args: argparse.Namespace, scans: tuple[str, ...]) -> tuple:
    """``--results`` of dit-register-scene: ``(log, known, on_result)`` for :func:`dit_jax.scenes.scene.register_scene`,
    the pairs of these scans the log holds under this run's settings, and the callback that appends each new
    one; ``(None, None, None)`` without --results."""
    from dit_jax.cli import results_log
    from dit_jax.pipeline.result import Result

    key = {**results_log.settings_key(args.checkpoint, settings.changes(args), files.reading_key(args)), "job": "scene"}
    pairs = [(s, t) for s in scans for t in scans if s != t]
    log = files.open_results(args, pairs, key, SCENE_PROG)
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
    from dit_jax.scenes import scene

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
    from dit_jax.geometry.rigid import rotation_angle_deg

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


command = files.console_script(main)


if __name__ == "__main__":
    command()
