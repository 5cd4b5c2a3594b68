"""A scene from its scans (:mod:`dit_jax.scene`): candidate pairs, edges by the verdict, the spanning tree's
first poses, the pose graph's optimisation that switches a wrong loop edge off, and scans that join nothing."""

import numpy as np
import pytest
from conftest import exact_result

from dit_jax import scene
from dit_jax.data.pairs import euler_zyx_to_matrix

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

    def register_scan_pairs(self, clouds, pairs, batch_size=8, on_pair=None):
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


def test_candidates_are_every_pair_for_few_scans_and_neighbours_and_overlaps_for_many(monkeypatch):
    clouds = [0.3 * np.random.default_rng(k).normal(size=(20, 3)) + [3.0 * k, 0, 0] for k in range(5)]
    assert scene.candidate_pairs(clouds) == [(s, t) for s in range(5) for t in range(s)]
    monkeypatch.setattr(scene, "ALL_PAIRS_SCANS", 3)
    assert scene.candidate_pairs(clouds) == [(1, 0), (2, 1), (3, 2), (4, 3)]
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[4, :3, 3] = [-12.0, 0, 0]  # placed where scan 0 is
    assert scene.candidate_pairs(clouds, poses) == [(1, 0), (2, 1), (3, 2), (4, 0), (4, 3)]


def test_a_scene_is_placed_by_its_edges_and_a_wrong_loop_edge_is_switched_off():
    clouds, truth = _views(6)
    registrar = _Registrar(clouds, np.stack([_pose(k) for k in range(6)]), wrong={(4, 1): (30.0, "unconfirmed")})
    done = []
    built = scene.register_scene(registrar, clouds, on_pair=done.append)
    assert len(registrar.asked) == sum(done) == 15 and built.placed.all() and built.components == (tuple(range(6)),)
    np.testing.assert_allclose(built.poses, truth, atol=1e-6)
    wrong = next(e for e in built.edges if (e.source, e.target) == (4, 1))
    assert not wrong.kept and not wrong.certain, "the line process switches the wrong loop edge off"
    assert all(e.kept for e in built.edges if (e.source, e.target) != (4, 1))
    assert all(e.certain == (e.result.level == "trusted") for e in built.edges)
    merged = built.merged(clouds)
    assert merged.shape == (sum(len(c) for c in clouds), 3)


def test_a_scan_that_joins_nothing_is_reported_not_forced_in():
    clouds, truth = _views(4)
    wrong = {(3, t): (90.0, "probably wrong", 0.2) for t in range(3)}  # laying little of scan 3 on the others
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


def test_dit_register_scene_writes_the_scene_and_says_what_it_left_out(tmp_path, monkeypatch, capsys):
    import json

    from dit_jax import cli, io, registration

    clouds, truth = _views(4)
    paths = []
    for k, cloud in enumerate(clouds):
        paths.append(str(tmp_path / f"scan{k}.ply"))
        io.write(paths[-1], cloud)
    read_back = [io.read(p) for p in paths]
    wrong = {}
    monkeypatch.setattr(
        registration, "load", lambda *a, **k: _ByContent(read_back, np.stack([_pose(k) for k in range(4)]), wrong)
    )
    names = ("scene.ply", "poses.json", "kitti.txt", "tum.txt", "scene.html")
    out, poses, kitti, tum, page = (str(tmp_path / name) for name in names)
    args = [*paths, "--out", out, "--voxel", "0.05", "--poses", poses, "--kitti", kitti, "--tum", tum, "--no-progress"]
    args += ["--plot", page]
    assert cli.scene_main(args) == 0
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

    wrong.update({(3, t): (90.0, "probably wrong", 0.2) for t in range(3)})
    assert cli.scene_main([*paths, "--no-progress"]) == cli.EXIT_SUSPECT
    assert f"{paths[3]} joins no scan of the scene: left out" in capsys.readouterr().err
    assert cli.scene_main([*paths, "--no-progress", "--no-verdict-status"]) == 0

    for bad, message in (
        ([paths[0]], "a scene needs at least 2 scans"),
        ([*paths, "--out", paths[1]], paths[1]),
        ([*paths, "--kitti", str(tmp_path / "no" / "k.txt")], "its folder does not exist"),
        ([*paths, "--voxel", "0"], "--voxel must be positive"),
        ([*paths, "--plot", str(tmp_path / "scene.png")], "expected a .html file name"),
    ):
        capsys.readouterr()
        assert cli.scene_main(bad) == 2
        err = capsys.readouterr().err
        assert err.startswith("dit-register-scene: error:") and message in err, err


def test_a_probably_wrong_result_that_lays_most_of_its_source_on_the_target_is_an_uncertain_edge():
    """The verdict is strict: where such a result is right, it joins its scans; where it is wrong, the line
    process switches it off."""
    clouds, truth = _views(5)
    poses = np.stack([_pose(k) for k in range(5)])
    # Scan 4 reaches the others through probably-wrong results only: right ones onto 3 and 2, a wrong one onto 0.
    wrong = {
        (4, 3): (0.0, "probably wrong", 0.8),
        (4, 2): (0.0, "probably wrong", 0.7),
        (4, 1): (0.0, "probably wrong", 0.1),
    }
    wrong[(4, 0)] = (40.0, "probably wrong", 0.6)
    built = scene.register_scene(_Registrar(clouds, poses, wrong=wrong), clouds)
    assert built.placed.all()
    np.testing.assert_allclose(built.poses, truth, atol=1e-6)
    edges = {(e.source, e.target): e for e in built.edges}
    assert not edges[(4, 3)].certain and edges[(4, 3)].kept and edges[(4, 2)].kept
    assert not edges[(4, 0)].kept, "the wrong one is switched off"
    assert [(e.source, e.target) for e in built.rejected] == [(4, 1)]
