"""A scene from its scans (:mod:`dit_jax.scenes.scene`): candidate pairs, edges by the verdict, the spanning tree's
first poses, the pose graph's optimisation that switches a wrong loop edge off, and scans that join nothing."""

import numpy as np
import pytest
from conftest import exact_result, scan_set

from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.scenes import plan, scene

pytest.importorskip("open3d", reason="the pose graph is Open3D's")


def _room(seed: int = 0) -> np.ndarray:
    """(N, 3) points on the floor and three walls of a 4 x 3 x 2.5 room, 2 cm apart on average."""
    rng = np.random.default_rng(seed)
    faces = []
    for axis, value, extent in ((2, 0.0, (4, 3)), (0, 0.0, (3, 2.5)), (0, 4.0, (3, 2.5)), (1, 3.0, (4, 2.5))):
        uv = rng.uniform(0, 1, size=(8000, 2)) * extent
        point = np.insert(uv, axis, value, axis=1)
        faces.append(point)
    return np.concatenate(faces) + rng.normal(scale=0.002, size=(32000, 3))


def _pose(k: int) -> np.ndarray:
    """Scan k's pose (its points into the room's frame): a camera walking along the room, turning."""
    pose = np.eye(4)
    pose[:3, :3] = euler_zyx_to_matrix([25.0 * k, 5.0 * (k % 3), -3.0 * k])
    pose[:3, 3] = [0.5 * k, 0.3 * np.sin(k), 0.1 * k]
    return pose


def _views(n: int) -> tuple[list[np.ndarray], np.ndarray]:
    """n overlapping views of the room (slabs along its length), each in its own frame; (clouds, poses)."""
    room = _room()
    poses = np.stack([_pose(k) for k in range(n)])
    clouds = []
    for k in range(n):
        inside = (room[:, 0] >= 0.5 * k) & (room[:, 0] <= 0.5 * k + 2.0)
        part = room[inside]
        inverse = np.linalg.inv(poses[k])
        clouds.append(part @ inverse[:3, :3].T + inverse[:3, 3])
    # Poses into scan 0's frame, as the scene reports them.
    return clouds, np.linalg.inv(poses[0]) @ poses


class _Registrar:
    """Registers by the truth, but for the pairs it is told to get wrong (with the level it is told)."""

    def __init__(self, clouds, poses, wrong=None):
        self.clouds, self.poses, self.wrong, self.asked = clouds, poses, wrong or {}, []

    def prepare_scans(self, clouds):
        return scan_set(clouds)

    def register_scan_pairs(self, scans, pairs, batch_size=8, on_pair=None):
        clouds = scan_set(scans).clouds
        return self.register_pairs([(clouds[s], clouds[t]) for s, t in pairs], batch_size, on_pair)

    def register_pairs(self, pairs, batch_size=8, on_pair=None):
        results = []
        for src, tgt in pairs:
            s = next(i for i, c in enumerate(self.clouds) if c is src)
            t = next(i for i, c in enumerate(self.clouds) if c is tgt)
            self.asked.append((s, t))
            truth = np.linalg.inv(self.poses[t]) @ self.poses[s]
            if (s, t) in self.wrong:
                turn, level, *fitness = self.wrong[(s, t)]
                wrong = np.eye(4)
                wrong[:3, :3] = euler_zyx_to_matrix([turn, 0.0, 0.0])
                results.append(exact_result(truth @ wrong, level, *fitness))
            else:
                results.append(exact_result(truth, "trusted" if s == t + 1 else "unconfirmed"))
            if on_pair is not None:
                on_pair(1)
        return results


def test_a_scene_registers_neighbours_then_the_pairs_its_groups_lay_over_each_other():
    assert plan.neighbour_pairs(5) == [(1, 0), (2, 0), (2, 1), (3, 0), (3, 1), (3, 2), (4, 1), (4, 2), (4, 3)]
    assert plan.neighbour_pairs(1) == []
    clouds = [0.3 * np.random.default_rng(k).normal(size=(200, 3)) + [3.0 * k, 0, 0] for k in range(5)]
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[4, :3, 3] = [-12.0, 0, 0]  # placed where scan 0 is
    asked = set(plan.neighbour_pairs(5))
    assert plan.overlap_pairs(clouds, poses, [range(5)], 0.05, asked) == [(4, 0)]
    assert plan.overlap_pairs(clouds, poses, [[0, 1, 2], [3, 4]], 0.05, asked) == [], "only within a group"
    assert plan.overlap_pairs(clouds, poses, [range(5)], 0.05, asked | {(4, 0)}) == [], "each pair once"


def test_a_scene_is_placed_by_its_edges_and_a_wrong_loop_edge_is_switched_off():
    clouds, truth = _views(6)
    registrar = _Registrar(clouds, np.stack([_pose(k) for k in range(6)]), wrong={(4, 1): (30.0, "unconfirmed")})
    done, planned = [], []
    built = scene.register_scene(registrar, clouds, on_pair=done.append, on_planned=planned.append)
    assert len(registrar.asked) == sum(done) == sum(planned) and planned[0] == 12, "the neighbours first"
    assert built.placed.all() and built.components == (tuple(range(6)),) and built.frame == 0
    np.testing.assert_allclose(built.poses, truth, atol=1e-6)
    wrong = next(e for e in built.edges if (e.source, e.target) == (4, 1))
    assert not wrong.kept and not wrong.certain, "the line process switches the wrong loop edge off"
    assert all(e.kept for e in built.edges if (e.source, e.target) != (4, 1))
    assert all(e.certain == (e.result.level == "trusted") for e in built.edges)
    merged = built.merged(clouds)
    assert merged.shape == (sum(len(c) for c in clouds), 3)


def test_a_scan_that_joins_nothing_is_reported_not_forced_in():
    clouds, truth = _views(4)
    wrong = {(3, t): (90.0 + 60.0 * t, "probably wrong", 0.2) for t in range(3)}  # each wrong its own way
    registrar = _Registrar(clouds, np.stack([_pose(k) for k in range(4)]), wrong=wrong)
    built = scene.register_scene(registrar, clouds)
    assert built.components == ((0, 1, 2), (3,)) and built.placed.tolist() == [True, True, True, False]
    assert {(e.source, e.target) for e in built.rejected} == set(wrong) and not any(e.kept for e in built.rejected)
    np.testing.assert_allclose(built.poses[:3], truth[:3], atol=1e-6)
    np.testing.assert_array_equal(built.poses[3], np.eye(4))
    assert len(built.merged(clouds)) == sum(len(c) for c in clouds[:3])
    with pytest.raises(ValueError, match="at least 2 scans"):
        scene.register_scene(registrar, clouds[:1])


class _ByContent(_Registrar):
    """:class:`_Registrar` for clouds read back from files: each known by its first point."""

    def register_pairs(self, pairs, batch_size=8, on_pair=None):
        index = lambda cloud: int(np.argmin([np.abs(c[0] - cloud[0]).sum() for c in self.clouds]))
        originals = [(self.clouds[index(s)], self.clouds[index(t)]) for s, t in pairs]
        return super().register_pairs(originals, batch_size, on_pair)


def _scan_files(folder, n: int):
    """n views of the room (:func:`_views`) written to ``folder`` as PLY files: (clouds, truth, paths, the
    clouds read back)."""
    from dit_jax import io

    clouds, truth = _views(n)
    paths = [str(folder / f"scan{k}.ply") for k in range(n)]
    for path, cloud in zip(paths, clouds):
        io.write(path, cloud)
    return clouds, truth, paths, [io.read(p) for p in paths]


def test_dit_register_scene_writes_the_scene_and_says_what_it_left_out(tmp_path, monkeypatch, capsys):
    import json

    from dit_jax import io
    from dit_jax.cli import files
    from dit_jax.cli import scene as scene_command
    from dit_jax.pipeline import registration

    clouds, truth, paths, read_back = _scan_files(tmp_path, 4)
    wrong = {}
    monkeypatch.setattr(
        registration, "load", lambda *a, **k: _ByContent(read_back, np.stack([_pose(k) for k in range(4)]), wrong)
    )
    names = ("scene.ply", "poses.json", "kitti.txt", "tum.txt", "scene.html")
    out, poses, kitti, tum, page = (str(tmp_path / name) for name in names)
    args = [*paths, "--out", out, "--voxel", "0.05", "--poses", poses, "--kitti", kitti, "--tum", tum, "--no-progress"]
    args += ["--plot", page]
    assert scene_command.main(args) == 0
    report = json.loads(open(poses).read())
    assert report["scans"] == paths and report["placed"] == [True] * 4 and len(report["edges"]) == 6
    np.testing.assert_allclose(report["poses"], truth, atol=1e-5)
    rows = np.loadtxt(kitti)
    assert rows.shape == (4, 12)
    np.testing.assert_allclose(rows.reshape(4, 3, 4), truth[:, :3], atol=1e-5)
    assert np.loadtxt(tum).shape == (4, 8)
    merged = io.read(out)
    assert 0 < len(merged) < sum(len(c) for c in clouds), "thinned to one point per 5-cm cell"
    assert (
        "edges: 6 pairs registered, 6 kept, 0 switched off by the optimisation, 0 probably wrong"
        in capsys.readouterr().out
    )

    wrong.update({(3, t): (90.0 + 60.0 * t, "probably wrong", 0.2) for t in range(3)})
    assert scene_command.main([*paths, "--no-progress"]) == files.EXIT_SUSPECT
    err = capsys.readouterr().err
    assert f"{paths[3]} joins no scan of the scene: left out" in err and "form 2 groups (3, 1 scans)" in err
    assert scene_command.main([*paths, "--no-progress", "--no-verdict-status"]) == 0

    for bad, message in (
        ([paths[0]], "a scene needs at least 2 scans"),
        ([*paths, "--out", paths[1]], paths[1]),
        ([*paths, "--kitti", str(tmp_path / "no" / "k.txt")], "its folder does not exist"),
        ([*paths, "--voxel", "0"], "--voxel must be positive"),
        ([*paths, "--plot", str(tmp_path / "scene.jpg")], "expected a .html or .png file name"),
    ):
        capsys.readouterr()
        assert scene_command.main(bad) == 2
        err = capsys.readouterr().err
        assert err.startswith("dit-register-scene: error:") and message in err, err


def test_two_groups_stay_apart_each_in_its_own_frame_the_larger_the_scene():
    """A probably wrong result is no edge however much of its source it lays on the target: scans 0 and 1 reach
    the rest only through such results, which place the two groups each in another way, so they form a group of
    their own."""
    clouds, _ = _views(5)
    poses = np.stack([_pose(k) for k in range(5)])
    wrong = {(s, t): (30.0 * (s + 2 * t), "probably wrong", 0.9) for s in (2, 3, 4) for t in (0, 1)}
    built = scene.register_scene(_Registrar(clouds, poses, wrong=wrong), clouds)
    assert built.components == ((2, 3, 4), (0, 1)) and built.frame == 2
    assert built.placed.tolist() == [False, False, True, True, True] and built.component_of(1) == 1
    in_frame = lambda frame, k: np.linalg.inv(poses[frame]) @ poses[k]  # noqa: E731
    for k in (2, 3, 4):
        np.testing.assert_allclose(built.poses[k], in_frame(2, k), atol=1e-6)
    np.testing.assert_allclose(built.poses[1], in_frame(0, 1), atol=1e-6)
    np.testing.assert_allclose(built.poses[0], np.eye(4), atol=1e-12)
    rejected = {(e.source, e.target) for e in built.rejected}
    assert rejected == set(wrong), "(4, 0), no neighbour pair, is registered to bridge the groups"
    assert not any(e.kept for e in built.rejected)
    report = built.to_json([f"s{k}" for k in range(5)])
    assert report["frame"] == "s2" and report["component"] == [1, 1, 0, 0, 0]
    assert len(built.merged(clouds)) == sum(len(c) for c in clouds[2:])


def test_two_groups_join_where_registrations_the_verdict_doubts_agree_on_how():
    """Right results of low-overlap pairs are often found probably wrong, wrong ones scatter: two such results
    that place the groups alike join them, as uncertain edges; a third that disagrees stays out."""
    clouds, truth = _views(5)
    poses = np.stack([_pose(k) for k in range(5)])
    doubted = {(s, t): (0.0, "probably wrong", 0.4) for s, t in ((2, 0), (3, 0), (3, 1), (4, 1))}
    doubted[(2, 1)] = (45.0, "probably wrong", 0.4)
    built = scene.register_scene(_Registrar(clouds, poses, wrong=doubted), clouds)
    assert built.components == (tuple(range(5)),)
    np.testing.assert_allclose(built.poses, truth, atol=1e-6)
    links = {(e.source, e.target) for e in built.edges if e.result.level == "probably wrong"}
    assert links == set(doubted) - {(2, 1)} and not any(e.certain for e in built.edges if (e.source, e.target) in links)
    assert {(e.source, e.target) for e in built.rejected} == {(2, 1)}


def test_doubted_registrations_whose_features_saw_a_rival_never_link_groups():
    """A repeated structure makes wrong registrations agree: where the features saw a rival motion past the
    verdict's bound, agreement between doubted registrations joins nothing."""
    import dataclasses

    clouds, _ = _views(5)
    poses = np.stack([_pose(k) for k in range(5)])
    doubted = {(s, t): (0.0, "probably wrong", 0.4) for s, t in ((2, 0), (3, 0), (3, 1), (4, 0), (4, 1))}
    doubted[(2, 1)] = (45.0, "probably wrong", 0.4)
    registrar = _Registrar(clouds, poses, wrong=doubted)
    plain = registrar.register_pairs

    def with_rivals(pairs, batch_size=8, on_pair=None):
        found = plain(pairs, batch_size, on_pair)
        return [dataclasses.replace(r, rival=0.9, max_rival=0.5) if r.level == "probably wrong" else r for r in found]

    registrar.register_pairs = with_rivals
    built = scene.register_scene(registrar, clouds)
    assert built.components == ((2, 3, 4), (0, 1))
    assert not any(e.result.level == "probably wrong" for e in built.edges)


def test_a_resumed_scene_takes_the_pairs_it_has_and_builds_the_same_scene():
    clouds, truth = _views(6)
    poses = np.stack([_pose(k) for k in range(6)])
    wrong = {(4, 1): (30.0, "unconfirmed")}
    first, written = _Registrar(clouds, poses, wrong=wrong), {}
    whole = scene.register_scene(first, clouds, batch_size=4, on_result=written.__setitem__)
    assert list(written) == first.asked, "every registered pair is handed over, in order"
    kept = dict(list(written.items())[:5])  # a run killed after five pairs
    again, done = _Registrar(clouds, poses, wrong=wrong), []
    resumed = scene.register_scene(again, clouds, batch_size=4, known=kept, on_pair=done.append)
    assert again.asked == first.asked[5:] and sum(done) == len(first.asked), "the bar counts the pairs taken too"
    np.testing.assert_allclose(resumed.poses, whole.poses, atol=1e-12)
    assert resumed.components == whole.components
    assert [(e.source, e.target, e.kept) for e in resumed.edges] == [(e.source, e.target, e.kept) for e in whole.edges]


def test_dit_register_scene_resumes_from_its_results_file_after_a_kill(tmp_path, monkeypatch, capsys):
    import json

    from dit_jax.cli import scene as scene_command
    from dit_jax.pipeline import registration

    _, truth, paths, read_back = _scan_files(tmp_path, 5)
    registrars = []

    def load(*_, **__):
        registrars.append(_ByContent(read_back, np.stack([_pose(k) for k in range(5)])))
        return registrars[-1]

    monkeypatch.setattr(registration, "load", load)
    log, poses = str(tmp_path / "pairs.jsonl"), str(tmp_path / "poses.json")
    args = [*paths, "--results", log, "--poses", poses, "--no-progress"]
    assert scene_command.main(args) == 0
    whole = json.loads(open(poses).read())
    lines = open(log).read().splitlines()
    assert len(lines) == len(registrars[0].asked) and json.loads(lines[0])["level"] == "trusted"

    assert scene_command.main(args) == 0 and registrars[1].asked == [], "every pair is taken from the file"
    assert open(log).read().splitlines() == lines, "nothing is added for pairs the file holds"

    # A run killed mid-write: the first three records and half of the fourth.
    open(log, "w").write("\n".join(lines[:3]) + "\n" + lines[3][:40])
    capsys.readouterr()
    assert scene_command.main(args) == 0
    assert "its last line is cut short; left as it is" in capsys.readouterr().err
    assert registrars[2].asked == registrars[0].asked[3:]
    again = open(log).read().splitlines()
    assert again[:4] == [*lines[:3], lines[3][:40]], "what was there stays"
    assert len(again) == len(lines) + 1
    np.testing.assert_allclose(json.loads(open(poses).read())["poses"], whole["poses"], atol=1e-12)
    np.testing.assert_allclose(whole["poses"], truth, atol=1e-5)

    for bad, message in (
        ([*paths[:3], "--results", log], "--reuse-results"),  # the file holds pairs of scans not given
        ([*paths, "--results", paths[0]], "it is one of the scans"),
        ([*paths, "--reuse-results"], "--reuse-results goes with --results"),
    ):
        capsys.readouterr()
        assert scene_command.main(bad) == 2
        assert message in capsys.readouterr().err
    assert scene_command.main([*paths[:3], "--results", log, "--reuse-results", "--no-progress"]) == 0
    assert registrars[-1].asked == [], "the pairs of the three scans are in the file"
