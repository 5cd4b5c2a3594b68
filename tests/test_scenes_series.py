"""A series of scans in one frame: chained motions, the loop's gap measured and spread, `dit-register-series`."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from conftest import exact_result

from dit_jax import io
from dit_jax.cli import series as series_command
from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.geometry import rigid
from dit_jax.scenes import series


def _pose(angles, translation):
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = euler_zyx_to_matrix(angles), translation
    return pose


def _turntable(k=8):
    """Poses of k scans of a full turn (each into scan 0's frame) and the loop's k true motions."""
    poses = np.stack([_pose([360.0 * i / k, 3.0 * np.sin(i), 0.0], [np.cos(i), 0.2 * i, -0.1 * i]) for i in range(k)])
    poses = np.linalg.inv(poses[0]) @ poses
    motions = np.stack([np.linalg.inv(poses[i]) @ poses[(i + 1) % k] for i in range(k)])
    return poses, motions


def _rotation_errors(poses, truth):
    return np.array([rigid.rotation_angle_deg(p[:3, :3].T @ q[:3, :3]) for p, q in zip(poses, truth)])


def test_exact_motions_chain_to_the_true_poses_and_close_with_no_gap():
    truth, motions = _turntable()
    np.testing.assert_allclose(series.chain(motions[:-1]), truth, atol=1e-12)
    poses, gap_deg, gap = series.close_loop(motions)
    np.testing.assert_allclose(poses, truth, atol=1e-9)
    assert gap_deg < 1e-6 and gap < 1e-9


def test_closing_the_loop_spreads_one_wrong_link_over_all():
    """One link 4 degrees and 0.3 off: the chain carries the whole error to every later scan; the loop
    measures it and leaves each scan at most about (K - 1) / K of it, the worst scans far less."""
    truth, motions = _turntable(8)
    wrong = motions.copy()
    wrong[2] = wrong[2] @ _pose([4.0, 0.0, 0.0], [0.3, 0.0, 0.0])
    chained = series.chain(wrong[:-1])
    poses, gap_deg, gap = series.close_loop(wrong)
    assert gap_deg == pytest.approx(4.0, abs=0.01) and 0.2 < gap < 0.6  # 0.3, and the turn's lever
    np.testing.assert_array_equal(poses[0], np.eye(4))
    before, after = _rotation_errors(chained, truth), _rotation_errors(poses, truth)
    assert before[3:].min() == pytest.approx(4.0, abs=0.01)  # every scan after the wrong link
    assert after.max() < 0.7 * before.max() and after.mean() < 0.7 * before.mean(), (before, after)
    shift_before = np.linalg.norm(chained[:, :3, 3] - truth[:, :3, 3], axis=1)
    shift_after = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert shift_after.mean() < 0.7 * shift_before.mean(), (shift_before, shift_after)
    # The closed poses are consistent around the loop: the last scan's pose and the last link give scan 0.
    np.testing.assert_allclose(poses[-1] @ motions[-1], np.eye(4), atol=0.15)

    # Fitted where the scans are (an object 3 units from the first scanner, as a turntable's is): the links
    # agree with the poses better than with the closed form's, by the measure the fit minimises, and exact
    # links still give the truth.
    target = np.array([3.0, 0.5, 0.0])
    centres = np.stack([np.linalg.inv(pose)[:3, :3] @ target + np.linalg.inv(pose)[:3, 3] for pose in truth])
    fitted, fitted_gap_deg, _ = series.close_loop(wrong, centres, scale=1.0)
    assert fitted_gap_deg == gap_deg
    np.testing.assert_array_equal(fitted[0], np.eye(4))
    misfit = {
        name: float(np.sum(series.link_misfit(p, wrong, centres, 1.0) ** 2))
        for name, p in (("fitted", fitted), ("closed", poses))
    }
    assert misfit["fitted"] < misfit["closed"], misfit  # (here the closed form is within 1 % of the best)
    assert np.abs(series.link_misfit(truth, motions, centres, 1.0)).max() < 1e-9
    exact, _, _ = series.close_loop(motions, centres, scale=1.0)
    np.testing.assert_allclose(exact, truth, atol=1e-9)


class _ExactRegistrar:
    """Registers by the truth (scan k's pose), as a perfect model would; records what it was asked."""

    def __init__(self, poses):
        self.poses, self.calls = poses, []

    def register(self, src, tgt, refine=None):

        a = next(i for i, c in enumerate(self.clouds) if c is src)
        b = next(i for i, c in enumerate(self.clouds) if c is tgt)
        self.calls.append((a, b, refine))
        motion = np.linalg.inv(self.poses[b]) @ self.poses[a]
        return exact_result(motion, "trusted" if a != 3 else "probably wrong", fitness=1.0)


def test_register_series_links_neighbours_and_merges_into_the_first_frame():
    truth, _ = _turntable(5)
    shape = np.random.default_rng(0).normal(size=(50, 3))
    clouds = [shape @ np.linalg.inv(p)[:3, :3].T + np.linalg.inv(p)[:3, 3] for p in truth]  # scan k's view
    registrar = _ExactRegistrar(truth)
    registrar.clouds = clouds
    done = []
    result = series.register_series(
        registrar, clouds, loop=True, refine="none", progress=lambda d, n: done.append((d, n))
    )
    assert [c[:2] for c in registrar.calls] == [(1, 0), (2, 1), (3, 2), (4, 3), (0, 4)] == result.pairs
    assert {c[2] for c in registrar.calls} == {"none"} and done[-1] == (5, 5)
    np.testing.assert_allclose(result.poses, truth, atol=1e-9)
    assert result.suspect_links == result.wrong_links == [2]  # the link from scan 3
    np.testing.assert_allclose(result.merged(clouds), np.tile(shape, (5, 1)), atol=1e-9)
    open_series = series.register_series(registrar, clouds[:3])
    assert np.isnan(open_series.loop_gap_deg) and len(open_series.links) == 2
    with pytest.raises(ValueError, match="at least 3 clouds for a loop"):
        series.register_series(registrar, clouds[:2], loop=True)
    with pytest.raises(ValueError, match="3 clouds for a series of 5"):
        result.apply(clouds[:3])


def test_dit_register_series_prints_poses_and_verdicts_and_writes_the_merged_cloud(capsys, tmp_path, tiny_checkpoint):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = d * (1 + 0.2 * np.sin(3 * d[:, :1]) * np.cos(2 * d[:, 1:2])) * 20.0
    paths = []
    for k in range(3):
        path = tmp_path / f"scan{k}.ply"
        io.write(path, surface @ euler_zyx_to_matrix([10.0 * k, 0.0, 0.0]).T + [k, 0.0, 0.0])
        paths.append(str(path))
    code = series_command.main(
        paths
        + [
            "--checkpoint",
            tiny_checkpoint,
            "--loop",
            "--refine",
            "none",
            "--json",
            "--out",
            str(tmp_path / "merged.ply"),
            "--out-dir",
            str(tmp_path / "aligned"),
            "--plot",
            str(tmp_path / "series.png"),
        ]
    )
    out, err = capsys.readouterr()
    report = json.loads(out)
    for path, pose in zip(paths, np.array(report["poses"])):  # each scan in the first one's frame, its own file
        np.testing.assert_allclose(
            io.read(tmp_path / "aligned" / os.path.basename(path)),
            io.read(path) @ pose[:3, :3].T + pose[:3, 3],
            atol=1e-9,
        )
    assert len(report["poses"]) == 3 and len(report["links"]) == 3
    assert [(link["source"], link["target"]) for link in report["links"]] == [
        (paths[1], paths[0]),
        (paths[2], paths[1]),
        (paths[0], paths[2]),
    ]
    assert report["loop_gap_deg"] is not None
    assert report["plot"] == str(tmp_path / "series.png")
    assert (tmp_path / "series.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_allclose(report["poses"][0], np.eye(4), atol=1e-12)
    assert io.read(tmp_path / "merged.ply").shape == (1200, 3)
    suspect = [link for link in report["links"] if link["level"] == "probably wrong"]
    assert code == (3 if suspect or report["loop_gap_deg"] > series_command.LOOP_GAP_WARNING_DEG else 0), err
    code = series_command.main(paths[:2] + ["--loop"])
    assert code == 2 and "--loop needs at least 3 scans" in capsys.readouterr().err
    code = series_command.main(paths + ["--plot", str(tmp_path / "series.jpg")])
    assert code == 2 and "expected a .png file name" in capsys.readouterr().err
    code = series_command.main(paths + ["--out-dir", str(tmp_path)])
    assert code == 2 and f"it holds {paths[0]}, which the moved scan would overwrite" in capsys.readouterr().err
    code = series_command.main([paths[0], str(tmp_path / "missing.ply")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"dit-register-series: error: {tmp_path / 'missing.ply'}: no such file")
    io.write(tmp_path / "scan1_mm.ply", io.read(paths[1]) * 1000.0)  # a unit slip: one line naming both scans
    series_command.main([paths[0], str(tmp_path / "scan1_mm.ply"), "--checkpoint", tiny_checkpoint, "--refine", "none"])
    warned = [line for line in capsys.readouterr().err.splitlines() if "times the size" in line]
    assert warned and all(
        line.startswith(f"dit-register-series: warning: {tmp_path / 'scan1_mm.ply'} is 1,0")
        and f"times the size of {paths[0]} (radius" in line
        for line in warned
    ), warned
