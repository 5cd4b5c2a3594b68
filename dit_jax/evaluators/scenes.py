"""Scenes (:mod:`dit_jax.scenes.scene`) against the 3DMatch benchmark's truth: each scene folder's fragments placed by
the pose graph, then every benchmark pair's motion read off the placed poses, beside the pairwise pipeline's
own result for the same pair (registered on the way), and each fragment's pose beside the truth chained
through both lists (:func:`dit_jax.data.scans.scene_poses`).

    python evaluate.py --scenes DIR_OF_3DMATCH_SCENES --out eval_scenes
"""

from __future__ import annotations

import json
import os
import pathlib
import time
from collections.abc import Sequence

import numpy as np

from dit_jax.evaluators.common import progress_bar
from dit_jax.geometry import rigid

#: A benchmark pair is registered within this rotation (degrees) and translation (the data's units, metres).
CRITERION = (15.0, 0.3)


def scene_folders(directory: str | os.PathLike) -> list[pathlib.Path]:
    """The 3DMatch scene folders under ``directory`` (each holds ``cloud_bin_*`` fragments and list folders
    with a ``gt.log``), or ``directory`` itself where it is one."""
    directory = pathlib.Path(directory)
    is_scene = lambda folder: any(folder.glob("cloud_bin_*")) and any(folder.glob("*/gt.log"))
    folders = (
        [directory] if is_scene(directory) else sorted(f for f in directory.iterdir() if f.is_dir() and is_scene(f))
    )
    if not folders:
        raise ValueError(f"{directory}: no 3DMatch scene (cloud_bin_* fragments and */gt.log lists)")
    return folders


def _right(estimate: np.ndarray, truth: np.ndarray) -> bool:
    """Whether a 4 x 4 ``estimate`` lies within :data:`CRITERION` of ``truth`` (as :func:`.scans.is_right`)."""
    from dit_jax.evaluators.scans import is_right

    degrees = rigid.rotation_angle_deg(estimate[:3, :3].T @ truth[:3, :3])
    return is_right({"rot_err": degrees, "trans_err": float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))}, CRITERION)


def _rmse_right(estimate: np.ndarray, truth: np.ndarray, info: np.ndarray | None) -> bool:
    """Whether ``estimate`` meets the benchmark's RMSE threshold (:func:`dit_jax.data.scans.benchmark_rmse`)."""
    from dit_jax.data import scans

    pair = scans.ScanPair("", None, None, truth[:3, :3], truth[:3, 3], info)
    return bool(scans.benchmark_rmse(estimate[:3, :3], estimate[:3, 3], pair) <= scans.BENCHMARK_RMSE)


def benchmark_pairs(folder: pathlib.Path) -> dict[str, list[tuple[int, int, np.ndarray]]]:
    """Each list's pairs of a scene folder, by list name: (i, j, the 4 x 4 motion of fragment j onto i)."""
    from dit_jax.data import scans

    return {log.parent.name: scans.read_gt_log(log) for log in sorted(folder.glob("*/gt.log"))}


def score_scene(folder: pathlib.Path, fragments: list[int], built, seconds: float, pairwise: dict) -> dict:
    """The figures of one scene ``built`` (:class:`dit_jax.scenes.scene.Scene`) from the ``fragments`` of ``folder``
    (their numbers, in the scene's order): a benchmark pair counts for the scene where one component holds both
    fragments and their poses in its frame give its motion; ``pairwise`` holds each benchmark pair's own
    result by (source, target) fragment numbers. Each fragment's pose error is measured in its component's
    frame, against the truth moved into the frame of the component's first fragment."""
    from dit_jax.data import scans

    truth, known = scans.scene_poses(folder)
    at = {fragment: k for k, fragment in enumerate(fragments)}
    lists = {}
    for name, pairs in benchmark_pairs(folder).items():
        log = folder / name / "gt.log"
        info = scans.read_gt_info(log.with_name("gt.info")) if log.with_name("gt.info").exists() else {}
        counts = {"pairs": 0, "scene": 0, "pairwise": 0, "scene_rmse": 0, "pairwise_rmse": 0}
        for i, j, motion in pairs:  # fragment j onto fragment i
            a, b = at[i], at[j]
            together = built.component_of(a) == built.component_of(b)
            from_scene = np.linalg.inv(built.poses[a]) @ built.poses[b]
            counts["pairs"] += 1
            counts["scene"] += together and _right(from_scene, motion)
            counts["pairwise"] += _right(pairwise[(j, i)].matrix, motion)
            counts["scene_rmse"] += together and _rmse_right(from_scene, motion, info.get((i, j)))
            counts["pairwise_rmse"] += _rmse_right(pairwise[(j, i)].matrix, motion, info.get((i, j)))
        lists[name] = {k: int(v) for k, v in counts.items()}
    position, rotation = [], []
    for component in built.components:
        first = fragments[component[0]]
        for k in component:
            if known[fragments[k]] and known[first]:
                expected = np.linalg.inv(truth[first]) @ truth[fragments[k]]
                position.append(float(np.linalg.norm(built.poses[k][:3, 3] - expected[:3, 3])))
                rotation.append(rigid.rotation_angle_deg(built.poses[k][:3, :3].T @ expected[:3, :3]))
    levels = {}
    for edge in (*built.edges, *built.rejected):
        levels[edge.result.level] = levels.get(edge.result.level, 0) + 1
    return {
        "scene": folder.name,
        "fragments": len(fragments),
        "placed": int(built.placed.sum()),
        "groups": [len(c) for c in built.components if len(c) > 1],
        "left_out": [fragments[k] for k in range(len(fragments)) if not built.placed[k]],
        "lists": lists,
        "position_rmse": float(np.sqrt(np.mean(np.square(position)))) if position else float("nan"),
        "position_max": max(position, default=float("nan")),
        "rotation_median_deg": float(np.median(rotation)) if rotation else float("nan"),
        "rotation_max_deg": max(rotation, default=float("nan")),
        "pairs_registered": len(built.edges) + len(built.rejected),
        "edges_kept": sum(e.kept for e in built.edges),
        "edges_switched_off": sum(not e.kept for e in built.edges),
        "rejected": len(built.rejected),
        "levels": levels,
        "seconds": seconds,
        "seconds_per_fragment": seconds / len(fragments),
    }


def evaluate_scenes(
    checkpoint_dir: str | None,
    directory: str | os.PathLike,
    out_dir: str,
    *,
    inference: dict | None = None,
    progress: bool = True,
    registrar=None,
    baselines: Sequence[str] = (),
) -> dict:
    """Each 3DMatch scene under ``directory`` (:func:`scene_folders`) placed by :func:`dit_jax.scenes.scene.register_scene`
    with a checkpoint (None: the shipped weights; ``inference``: changes to its settings; ``registrar``: one
    already loaded instead), timed, then each benchmark pair the scene did not register registered on its own
    (untimed), and all scored by :func:`score_scene`. Writes ``results.json`` and ``results.md`` to
    ``out_dir``, and a picture of each scene (``scene_NAME.png``); returns the results with their ``table``.
    ``baselines``: names of :data:`dit_jax.evaluators.scene_baselines.SCENE_BASELINES` placed and scored beside (each fragment
    in scan 0's frame, one group), under each row's ``baselines``; their pairs are logged in ``out_dir`` and a
    run given the same ``out_dir`` resumes them (:func:`baseline_log`)."""
    from dit_jax import io
    from dit_jax.pipeline import registration
    from dit_jax.scenes import scene

    registrar = registrar or registration.load(checkpoint_dir, **(inference or {}))
    rows = []
    for folder in scene_folders(directory):
        files = sorted(folder.glob("cloud_bin_*.*"), key=lambda f: int(f.stem.split("_")[-1]))
        fragments = [int(f.stem.split("_")[-1]) for f in files]
        clouds = [io.read(f) for f in files]
        bar = progress_bar(progress, 0, f"scene {folder.name}")
        started = time.perf_counter()
        built = scene.register_scene(registrar, clouds, **scene.progress(bar))
        seconds = time.perf_counter() - started
        if bar is not None:
            bar.close()
        pairwise = _pairwise(registrar, folder, fragments, clouds, built)
        rows.append(score_scene(folder, fragments, built, seconds, pairwise))
        rows[-1]["baselines"] = {
            name: _baseline(name, folder, fragments, clouds, pairwise, progress, out_dir) for name in baselines
        }
        os.makedirs(out_dir, exist_ok=True)
        picture = os.path.join(out_dir, f"scene_{folder.name}.png")
        names = [f"fragment {fragment}" for fragment in fragments]
        built.plot(
            picture,
            clouds,
            names,
            title=f"{folder.name}: the largest group, {int(built.placed.sum())} of {len(clouds)} fragments",
        )
    results = {"data": os.fspath(directory), "criterion": list(CRITERION), "scenes": rows}
    results["table"] = table(rows)
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump({k: v for k, v in results.items() if k != "table"}, f, indent=2)
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(results["table"] + "\n")
    return results


def _baseline(
    name: str, folder: pathlib.Path, fragments: list[int], clouds: list, pairwise: dict, progress: bool, out_dir
):
    """The figures of :data:`dit_jax.evaluators.scene_baselines.SCENE_BASELINES`' ``name`` on one scene, scored as a scene. Its
    pairs go to a log in ``out_dir`` (:func:`baseline_log`) as they finish; a run given a log that holds some
    takes them as they are and registers the rest. Its seconds are its pairs' own, as logged, and the rest of
    this run's (features of scans whose pairs were all logged are not computed again)."""
    from dit_jax.evaluators import scene_baselines
    from dit_jax.scenes import scene

    log = baseline_log(out_dir, name, folder)
    known = _logged_pairs(log, fragments)
    count = len(clouds) * (len(clouds) - 1) // 2
    bar = progress_bar(progress, count, f"{name} {folder.name}")
    new = []
    started = time.perf_counter()
    os.makedirs(out_dir, exist_ok=True)
    with open(log, "a+b") as f:
        if f.tell():  # a killed run's cut last line stays, ended, and is skipped on reading
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                f.write(b"\n")

        def logged(pair):
            new.append(pair)
            record = pair._replace(source=fragments[pair.source], target=fragments[pair.target]).to_record()
            f.write(json.dumps(record).encode() + b"\n")
            f.flush()

        poses = scene_baselines.SCENE_BASELINES[name](
            clouds, on_pair=bar.update if bar else None, known=known, on_result=logged
        )
    seconds = (
        time.perf_counter() - started - sum(p.seconds for p in new) + sum(p.seconds for p in (*known.values(), *new))
    )
    if bar is not None:
        bar.close()
    placed = scene.Scene(poses, (), (), (tuple(range(len(clouds))),))
    row = score_scene(folder, fragments, placed, seconds, pairwise)
    keep = ("lists", "position_rmse", "position_max", "rotation_median_deg", "rotation_max_deg", "seconds")
    return {key: row[key] for key in (*keep, "seconds_per_fragment")} | {"pairs_logged_before": len(known)}


def baseline_log(out_dir, name: str, folder: pathlib.Path) -> pathlib.Path:
    """The log of a scene baseline's pairs (:class:`dit_jax.evaluators.scene_baselines.MultiwayPair` records, one JSON line each,
    scans by fragment number): ``out_dir/NAME_SCENE.jsonl``. Appended to, never rewritten; delete it to
    register every pair again."""
    return pathlib.Path(out_dir) / f"{name}_{folder.name}.jsonl"


def _logged_pairs(log: pathlib.Path, fragments: list[int]) -> dict:
    """The pairs a :func:`baseline_log` holds, by (source, target) index into ``fragments`` (a cut line, a
    killed run's last, is skipped; a pair of fragments this scene lacks is refused)."""
    from dit_jax.evaluators import scene_baselines

    at = {fragment: k for k, fragment in enumerate(fragments)}
    known = {}
    for number, line in enumerate(log.read_text().splitlines() if log.exists() else (), 1):
        try:
            pair = scene_baselines.MultiwayPair.from_record(json.loads(line))
        except (ValueError, KeyError, TypeError):
            continue
        if pair.source not in at or pair.target not in at:
            raise ValueError(f"{log}:{number}: fragments {pair.source} and {pair.target} are not both in the scene")
        known[at[pair.source], at[pair.target]] = pair._replace(source=at[pair.source], target=at[pair.target])
    return known


def _pairwise(registrar, folder: pathlib.Path, fragments: list[int], clouds: list, built) -> dict:
    """Each benchmark pair's own result by (source, target) fragment numbers: the scene's where it registered
    the pair, else registered now."""
    registered = {(fragments[e.source], fragments[e.target]): e.result for e in (*built.edges, *built.rejected)}
    at = {fragment: k for k, fragment in enumerate(fragments)}
    wanted = {(j, i) for pairs in benchmark_pairs(folder).values() for i, j, _ in pairs}
    missing = sorted(wanted - set(registered))
    if missing:
        found = registrar.register_scan_pairs(clouds, [(at[j], at[i]) for j, i in missing])
        registered.update(zip(missing, found))
    return registered


def _baseline_cells(row: dict, list_name: str, name: str = "open3d_multiway") -> str:
    """The table's cells of the baseline ``name`` on one scene and list ('-' where it did not run)."""
    found = row.get("baselines", {}).get(name)
    if found is None:
        return " - | - | - |"
    return (
        f" {found['lists'][list_name]['scene']} | {found['position_rmse']:.3f} / {found['position_max']:.3f} |"
        f" {found['seconds_per_fragment']:.2f} |"
    )


def table(rows: list[dict]) -> str:
    """The scenes' figures as a Markdown table: per scene and list, the benchmark pairs within the criterion
    (and by the benchmark's RMSE) from the scene's poses and from the pairwise results; the fragments' pose
    errors; the edges; the time; and Open3D's multiway registration where a row has it."""
    multiway = any(row.get("baselines", {}).get("open3d_multiway") for row in rows)
    header = (
        "| scene | list | pairs | scene: within 15 deg, 0.3 m | pairwise | scene: RMSE <= 0.2 m | pairwise |"
        " fragments in the scene (groups) | position RMSE / max (m) | rotation median / max (deg) | pairs"
        " registered, edges kept, switched off, no edge | s per fragment |"
    )
    if multiway:
        header += " Open3D multiway: within 15 deg, 0.3 m | its position RMSE / max (m) | its s per fragment |"
    lines = [header, "|" + "---|" * header.count(" |")]
    for row in rows:
        for name, c in row["lists"].items():
            lines.append(
                f"| {row['scene']} | {name} | {c['pairs']} | {c['scene']} | {c['pairwise']} | {c['scene_rmse']} |"
                f" {c['pairwise_rmse']} | {row['placed']} of {row['fragments']}"
                f" ({', '.join(map(str, row['groups']))}) |"
                f" {row['position_rmse']:.3f} / {row['position_max']:.3f} |"
                f" {row['rotation_median_deg']:.2f} / {row['rotation_max_deg']:.2f} |"
                f" {row['pairs_registered']}, {row['edges_kept']}, {row['edges_switched_off']}, {row['rejected']} |"
                f" {row['seconds_per_fragment']:.2f} |" + (_baseline_cells(row, name) if multiway else "")
            )
    return "\n".join(lines)
