import importlib
import json
import os

import jax
import numpy as np
import pytest

from dit_jax import evaluators as evaluation
from dit_jax.data import scans as scans_lib
from dit_jax.evaluators import common, report, synthetic
from dit_jax.evaluators import scans as scans_evaluator
from dit_jax.network import checkpoint, configs, model
from dit_jax.pipeline import registration, settings


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "model"
    config = configs.tiny()
    checkpoint.save(
        path, model.init(jax.random.key(0), config), config, extra={"inference_settings": {"n_points": 128}}
    )
    return str(path)


def test_evaluate_end_to_end_writes_tables_json_and_plots(tiny_checkpoint, tmp_path, prepared_dir):
    names = ["icp"] if importlib.import_module("dit_jax.evaluators.baselines").available() else []
    out = tmp_path / "eval"
    evaluation.evaluate(
        tiny_checkpoint,
        str(out),
        settings=("clean", "high_noise_partial"),
        max_pairs=4,
        baselines=names,
        prepared_dir=prepared_dir,
        progress=False,
        authors_thresholds=True,
    )
    assert sorted(os.listdir(out)) == [
        "registrations.png",
        "results.json",
        "results.md",
        "success_ratio.png",
        "worst_clean.png",
        "worst_high_noise_partial.png",
    ]
    saved = json.loads((out / "results.json").read_text())
    assert saved["n_points"] == 128, "the checkpoint's inference point count is the default"
    for setting in ("clean", "high_noise_partial"):
        dit = saved["settings"][setting]["DIT"]
        assert dit["pairs"] == 4 and dit["seconds_per_pair"] > 0 and dit["chamfer"] >= 0
        assert saved["setting_info"][setting]["gmcce_threshold"] == configs.GMCCE_THRESHOLDS[setting]
        assert sum(c["pairs"] for c in dit["by_category"].values()) == 4
        assert list(saved["settings"][setting]) == ["DIT", "DIT+ICP", "pipeline", *names]
        pipeline_row = saved["settings"][setting]["pipeline"]
        assert pipeline_row["verdict"]["rule"] == "the pipeline's own verdict"
        assert 0 <= pipeline_row["feature_candidate_kept"] <= 4
        assert pipeline_row["seconds_per_pair"] >= saved["settings"][setting]["DIT+ICP"]["seconds_per_pair"]
        assert saved["settings"][setting]["DIT+ICP"]["seconds_per_pair"] > dit["seconds_per_pair"]
    assert "| DIT |" in (out / "results.md").read_text()
    assert (out / "success_ratio.png").stat().st_size > 10_000
    clean = saved["settings"]["clean"]
    for method in ("DIT", "DIT+ICP"):
        assert clean[method]["verdict"]["rule"].startswith("target onto source agrees within")
    # DIT+ICP keeps the better of its two directions (the default), and says how often the second.
    assert "backward_kept" in clean["DIT+ICP"]
    # Each pair's evidence is kept, so a later threshold can be scored on these pairs without rerunning them:
    # at the thresholds they were written with, re-scoring changes nothing; at a negative one it trusts nothing.
    assert clean["DIT"]["per_pair"]["pair"] == [0, 1, 2, 3] and len(clean["DIT+ICP"]["per_pair"]["agreement"]) == 4
    defaults = settings.InferenceSettings()
    written = {"none": defaults.max_disagreement_network, "icp": defaults.max_disagreement_icp}
    unchanged = evaluation.rescore_agreement(json.loads(json.dumps(saved)), written)
    assert json.dumps(unchanged, sort_keys=True) == json.dumps(saved, sort_keys=True)  # (NaN != NaN as a dict value)
    strict = evaluation.rescore_agreement(json.loads(json.dumps(saved)), {"none": -1.0, "icp": -1.0})
    for method in ("DIT", "DIT+ICP"):
        verdict = strict["settings"]["clean"][method]["verdict"]
        assert verdict["passed"] == 0 and verdict["rule"].endswith("within -1 deg")
        assert strict["settings"]["clean"][method]["rot_mae"] == clean[method]["rot_mae"]
    assert "within -1 deg" in report.markdown_tables(strict)
    assert len(clean["DIT"]["per_pair"]["fitness"]) == 4
    assert "DIT's verdict (target onto source agrees" in (out / "results.md").read_text()
    assert "DIT's verdict (fitness" in (out / "results.md").read_text()


def test_evaluate_runs_the_model_as_shipped_on_independent_settings(tiny_checkpoint, tmp_path, prepared_dir):
    """By default one inference setting for every data setting (the checkpoint's own); settings whose clouds
    share no point read every point of the shapes. (Run here with DIT+ICP keeping its better direction.)"""
    results = evaluation.evaluate(
        tiny_checkpoint,
        str(tmp_path / "e"),
        settings=("independent_clean", "scan_high_noise"),
        max_pairs=3,
        prepared_dir=prepared_dir,
        progress=False,
        inference={"best_direction": True},
    )
    for setting in ("independent_clean", "scan_high_noise"):
        assert results["setting_info"][setting]["gmcce_threshold"] == configs.tiny().gmcce_threshold
        assert results["settings"][setting]["DIT"]["pairs"] == 3
        # With best_direction, DIT+ICP reports how often it kept the target-onto-source registration.
        assert 0 <= results["settings"][setting]["DIT+ICP"]["backward_kept"] <= 3
    assert "the second on" in (tmp_path / "e" / "results.md").read_text()


def test_evaluate_scans_writes_a_row_per_pair(tiny_checkpoint, tmp_path):
    import numpy as np
    from conftest import random_rotation, write_scan_series

    rng = np.random.default_rng(0)
    write_scan_series(tmp_path, [(random_rotation(rng), rng.normal(size=3)) for _ in range(3)], rng, n_points=300)
    results = evaluation.evaluate_scans(
        tiny_checkpoint, str(tmp_path), str(tmp_path / "out"), skips=(1,), progress=False
    )
    rows = results["pair_sets"]["skip1"]["DIT"]["rows"]
    assert [r["pair"] for r in rows] == ["s0->s1", "s1->s2", "s2->s0"]
    assert all(0 <= r["rot_err"] <= 180 and 0 <= r["fitness"] <= 1 for r in rows)
    assert sorted(os.listdir(tmp_path / "out")) == [
        "results.json",
        "results.md",
        "success_ratio.png",
        "worst_skip1.png",
    ]
    assert "| DIT |" in results["table"] and "| DIT+ICP |" in results["table"] and "3 pairs" in results["table"]
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    strict = evaluation.rescore_agreement(saved, {"none": -1.0, "icp": -1.0})["pair_sets"]["skip1"]
    assert (
        not any(r["verdict"] for r in strict["DIT"]["rows"]) and strict["DIT+ICP"]["summary"]["verdict"]["passed"] == 0
    )
    assert [r["rot_err"] for r in strict["DIT"]["rows"]] == [r["rot_err"] for r in rows]


def test_evaluate_scans_reads_a_single_pair_with_its_benchmark_criterion(tiny_checkpoint, tmp_path):
    """A folder of source, target and T_target_source.txt (the LiDAR layout): one pair set, and the table
    counts the pairs registered by the benchmark's criterion (5 degrees, 2 m) beside the error columns."""
    import numpy as np
    from conftest import random_rotation

    from dit_jax import io

    rng = np.random.default_rng(2)
    cloud = rng.normal(size=(300, 3)) * [4.0, 2.0, 0.5]
    rotation, translation = random_rotation(rng), np.array([0.5, 0.1, 0.0])
    io.write(tmp_path / "source.ply", cloud)
    io.write(tmp_path / "target.ply", cloud @ rotation.T + translation)
    np.savetxt(tmp_path / "T_target_source.txt", np.vstack([np.c_[rotation, translation], [0, 0, 0, 1]]))
    results = evaluation.evaluate_scans(
        tiny_checkpoint,
        str(tmp_path),
        str(tmp_path / "out"),
        progress=False,
        inference={"refine": "none"},
        worst_pairs=False,
    )
    summary = results["pair_sets"]["pair"]["DIT"]["summary"]
    row = results["pair_sets"]["pair"]["DIT"]["rows"][0]
    assert summary["registered"] == int(row["rot_err"] <= 5.0 and row["trans_err"] <= 2.0)
    assert "| method | registered (5 deg, 2) |" in results["table"]
    assert results["pair_set_info"]["pair"]["criterion"] == [5.0, 2.0]


def test_evaluate_scans_scores_a_folder_of_3dmatch_scenes_as_the_benchmark_does(tiny_checkpoint, tmp_path):
    """Scenes of 3DMatch lists: each row carries the benchmark's RMSE, its scene and whether its fragments are
    consecutive; the summary's recall counts the non-consecutive pairs within 0.2 (pooled and per scene), the
    pipeline's levels how often each was right; a seeded sample takes pairs from every scene."""
    from conftest import write_3dmatch_scene

    from dit_jax.data.scans import BENCHMARK_RMSE

    rng = np.random.default_rng(5)
    world = rng.normal(size=(300, 3)) * [2.0, 1.5, 1.0]
    for scene in ("a", "b"):
        write_3dmatch_scene(tmp_path / "scenes" / scene, world, rng)
    results = evaluation.evaluate_scans(
        tiny_checkpoint, str(tmp_path / "scenes"), str(tmp_path / "out"), progress=False, worst_pairs=False
    )
    done = results["pair_sets"]["3DMatch"]
    for method in ("DIT", "pipeline"):
        rows, bench = done[method]["rows"], done[method]["summary"]["benchmark"]
        assert [r["scene"] for r in rows] == ["a"] * 3 + ["b"] * 3
        counted = [r for r in rows if not r["consecutive"]]
        assert bench["counted"] == len(counted) == 4
        assert bench["recall"] == pytest.approx(np.mean([r["rmse"] <= BENCHMARK_RMSE for r in counted]))
        assert bench["scenes"]["a"]["counted"] == 2
        assert bench["recall_scenes"] == pytest.approx(np.mean([bench["scenes"][s]["recall"] for s in "ab"]))
    levels = done["pipeline"]["summary"]["levels"]
    assert sum(v["pairs"] for v in levels.values()) == 6
    assert sum(v["right"] for v in levels.values()) == done["pipeline"]["summary"]["registered"]
    assert "registration recall (RMSE <= 0.2)" in results["table"] and "recall b" in results["table"]
    sample = scans_evaluator.sample_pairs(scans_lib.load_pair_sets(tmp_path / "scenes")["3DMatch"], 4, seed=1)
    assert len(sample) == 4 and {p.scene for p in sample} == {"a", "b"}


def test_evaluate_py_applies_or_refuses_every_flag_with_scans(tiny_checkpoint, tmp_path, capsys):
    """--points and --iters reach the scans' registrations; a flag that a mode would ignore is refused."""
    import numpy as np
    from conftest import random_rotation, write_scan_series

    import evaluate

    rng = np.random.default_rng(1)
    write_scan_series(tmp_path, [(random_rotation(rng), rng.normal(size=3)) for _ in range(2)], rng, n_points=300)
    out = tmp_path / "out"
    assert (
        evaluate.main(
            [
                "--checkpoint",
                tiny_checkpoint,
                "--scans",
                str(tmp_path),
                "--skips",
                "1",
                "--points",
                "96",
                "--iters",
                "2",
                "--refine",
                "none",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    dit = json.loads((out / "results.json").read_text())["dit"]
    assert (dit["n_points"], dit["n_iters"], dit["inference_settings"]["refine"]) == (96, 2, "none")
    assert "DIT sees 96 points of each scan" in (out / "results.md").read_text()
    for argv in (
        ["--scans", str(tmp_path), "--verdict", "fitness"],
        ["--scans", str(tmp_path), "--unseen"],
        ["--scans", str(tmp_path), "--angle-sweep"],
        ["--angle-sweep", "--iters", "2"],
        ["--angle-sweep", "--features", "on"],
        ["--skips", "3"],
    ):
        with pytest.raises(SystemExit):
            evaluate.main(argv + ["--out", str(tmp_path / "refused")])
        assert "does not apply" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the room recipe and the feature candidate alone register scans only
        evaluate.main(["--baselines", "open3d_room_5cm", "--out", str(tmp_path / "refused")])
    assert "only with --scans" in capsys.readouterr().err
    for argv in (["--scenes", str(tmp_path), "--baselines", "icp"], ["--baselines", "open3d_multiway"]):
        with pytest.raises(SystemExit):  # the multiway baseline places whole scenes, and scenes take it alone
            evaluate.main(argv + ["--out", str(tmp_path / "refused")])
        assert "only open3d_multiway, which takes whole scenes" in capsys.readouterr().err
    assert not (tmp_path / "refused").exists()


def test_angle_sweep_reports_every_angle(tiny_checkpoint, tmp_path):
    results = evaluation.angle_sweep(
        tiny_checkpoint, str(tmp_path), angles=(0, 90), pairs_per_angle=2, unseen=False, progress=False
    )
    assert set(results["angles"]) == {0.0, 90.0} and all(len(r["errors"]) == 2 for r in results["angles"].values())
    assert all(len(r["icp"]["errors"]) == 2 for r in results["angles"].values())
    assert (tmp_path / "angle_sweep.png").exists() and "| 90 |" in results["table"] and "DIT+ICP" in results["table"]
    gicp = evaluation.angle_sweep(
        tiny_checkpoint, str(tmp_path / "gicp"), angles=(0,), pairs_per_angle=2, unseen=False, progress=False,
        refine="gicp",
    )  # fmt: skip
    assert "DIT+GICP" in gicp["table"] and len(gicp["angles"][0.0]["icp"]["errors"]) == 2
    with pytest.raises(ValueError, match="refine must be one of"):
        evaluation.angle_sweep(tiny_checkpoint, str(tmp_path / "no"), refine="yes")


def test_evaluate_cli_reports_a_missing_checkpoint(tmp_path, capsys):
    import evaluate

    assert evaluate.main(["--checkpoint", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    assert "no such checkpoint directory" in capsys.readouterr().err


def test_evaluate_cli_uses_the_shipped_weights_by_default(tmp_path, capsys):
    import evaluate
    from dit_jax.pipeline import registration

    assert evaluate.main(["--max-pairs", "2", "--out", str(tmp_path), "--no-progress", "--verdict", "fitness"]) == 0
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["checkpoint"] == os.path.abspath(registration.shipped_weights())
    assert "verdict" not in saved["settings"]["clean"]["DIT"] and "verdict_fitness" in saved["settings"]["clean"]["DIT"]
    assert saved["n_points"] == registration.load().settings.n_points


def test_reuse_takes_baselines_scored_on_the_same_pairs(tmp_path, monkeypatch, prepared_dir):
    pytest.importorskip("open3d", reason="the baselines need Open3D")
    first = evaluation.evaluate(
        None,
        str(tmp_path / "a"),
        settings=("clean",),
        max_pairs=3,
        baselines=["icp"],
        prepared_dir=prepared_dir,
        progress=False,
    )

    def never(*args, **kwargs):
        raise AssertionError("a reused baseline was run again")

    monkeypatch.setattr(synthetic, "predict_baseline", never)
    again = evaluation.evaluate(
        None,
        str(tmp_path / "b"),
        settings=("clean",),
        max_pairs=3,
        baselines=["icp"],
        prepared_dir=prepared_dir,
        progress=False,
        reuse=str(tmp_path / "a"),
    )
    assert again["settings"]["clean"]["icp"] == json.loads(json.dumps(first["settings"]["clean"]["icp"]))
    with pytest.raises(ValueError, match="made on other pairs"):
        evaluation.evaluate(
            None,
            str(tmp_path / "c"),
            settings=("clean",),
            max_pairs=3,
            baselines=["icp"],
            prepared_dir=prepared_dir,
            progress=False,
            reuse=str(tmp_path / "a"),
            unseen=True,
        )


def test_reuse_reads_an_option_a_record_predates_at_its_default():
    """Scores stored before an option existed ran at its default: reused; a changed or vanished option is not."""
    now = synthetic._options("icp", "clean")
    predates = {k: v for k, v in now.items() if k != "face_origin"}
    assert not now["face_origin"]  # the default, which the stored run used
    assert synthetic._same_options(predates, "icp", "clean")
    assert not synthetic._same_options(predates | {"face_origin": True}, "icp", "clean")
    assert not synthetic._same_options(now | {"distance": now["distance"] * 2}, "icp", "clean")
    assert not synthetic._same_options(now | {"an_option_since_removed": 1}, "icp", "clean")
    assert not synthetic._same_options(None, "icp", "clean")


def test_refinement_never_makes_clean_pairs_worse_and_records_tuned_options(tmp_path, prepared_dir):
    """The shipped weights on clean pairs (DIT alone exact to about 1e-3 degrees): ICP after them makes no
    pair worse on average, and every baseline row records the options it ran with (tuned for the setting)."""
    from dit_jax.pipeline import registration

    baselines = importlib.import_module("dit_jax.evaluators.baselines")
    names = ["fpfh_ransac_icp"] if baselines.available() else []
    results = evaluation.evaluate(
        registration.shipped_weights(),
        str(tmp_path / "e"),
        settings=("clean",),
        max_pairs=4,
        baselines=names,
        prepared_dir=prepared_dir,
        progress=False,
        worst_pairs=False,
        inference={"verdict_rule": "fitness"},
    )
    rows = results["settings"]["clean"]
    assert rows["DIT"]["rot_iso"] < 0.01
    assert rows["DIT+ICP"]["rot_iso"] <= rows["DIT"]["rot_iso"] + 1e-6
    assert rows["DIT+ICP"]["refinement"]["good_within_goal"] == 4
    for name in names:
        assert rows[name]["options"] == baselines.tuned_options(name, "clean").to_dict()
        assert rows[name]["success"] == 1.0
    assert not any(f.startswith("worst_") for f in os.listdir(tmp_path / "e"))


def test_refinement_summary_counts_the_pairs_dit_had_close():
    summary = common.refinement_summary(
        __import__("numpy").array([2.0, 20.0, 8.0]), __import__("numpy").array([0.5, 30.0, 1.5])
    )
    assert (summary["good"], summary["good_within_goal"], summary["good_worst_after"]) == (2, 1, 1.5)
    assert summary["mean_before"] == 10.0 and "2 pairs DIT alone had within 10 deg, 1 end" in report.refinement_line(
        summary
    )


def test_refinement_summary_tells_misses_the_data_place_elsewhere():
    import numpy as np

    before, after = np.array([2.0, 5.0, 8.0, 30.0]), np.array([0.5, 3.0, 1.5, 2.0])
    summary = common.refinement_summary(before, after, np.array([False, True, False, True]))
    assert summary["good_missed_data"] == 1  # pair 2: a miss the data prefer; pair 4: DIT was not close
    assert "of the 2 that do not, 1 end where the clouds fit better" in report.refinement_line(summary)


def test_worst_pairs_picture_leaves_out_reused_methods_without_their_worst_pair(tmp_path):
    """A picture of worst pairs never shows an earlier run's estimate: a method whose reused scores lack
    their worst pair is left out (and named), the others are drawn."""
    import numpy as np

    rng = np.random.default_rng(0)
    pair = {"src": rng.normal(size=(32, 3)), "tgt": rng.normal(size=(32, 3)), "R": np.eye(3), "t": np.zeros(3)}
    scored = {
        "DIT": {"worst": {"pair": 0, "rot_err": 3.0, "R": np.eye(3).tolist(), "t": [0.0, 0.0, 0.0]}},
        "icp": {"rot_iso": 1.0},
    }
    path = tmp_path / "worst.png"
    missing = report.plot_worst_pairs([pair], scored, str(path), "worst pairs")
    assert missing == ["icp"]
    assert path.stat().st_size > 1000
    assert report.plot_worst_pairs([pair], {"icp": {}}, str(tmp_path / "none.png"), "t") == ["icp"]
    assert not (tmp_path / "none.png").exists(), "nothing drawable: no picture at all"


def test_evaluation_registers_each_pair_as_register_does(tiny_checkpoint, tmp_path, prepared_dir):
    """evaluate.py's DIT and DIT+ICP rows come from the same pipeline users call: on a test pair, the motion
    scored is the one ``register`` returns for that pair (the network's and the refined one)."""
    import jax.numpy as jnp

    from dit_jax.data import pairs as pairs_lib
    from dit_jax.data import shapes as shapes_lib
    from dit_jax.evaluators import metrics

    registrar = registration.load(tiny_checkpoint)
    results = evaluation.evaluate(
        tiny_checkpoint,
        str(tmp_path / "e"),
        settings=("independent_clean",),
        max_pairs=1,
        prepared_dir=prepared_dir,
        progress=False,
        worst_pairs=False,
    )
    n_points = registrar.settings.n_points
    shapes = shapes_lib.load_shapes(
        None, "test", data_dir=prepared_dir, n_points=pairs_lib.shape_points(None, n_points, ["independent_clean"])
    )
    pair = pairs_lib.PairDataset(shapes, pairs_lib.PairConfig(setting="independent_clean", n_points=n_points))[0]
    result = registrar.register(pair["src"], pair["tgt"])
    rows = results["settings"]["independent_clean"]
    for method, motion in (("DIT+ICP", result), ("DIT", result.stage("network"))):
        # the metric evaluate.py scores with, on the motion register returned
        expected = float(
            metrics.rotation_error_deg(jnp.asarray(motion.rotation[None]), jnp.asarray(pair["R"][None]))[0]
        )
        assert rows[method]["per_pair"]["rot_err"][0] == pytest.approx(expected, abs=1e-4), method
    assert rows["DIT+ICP"]["per_pair"]["agreement"][0] == pytest.approx(result.agreement, abs=1e-4)


class _SceneTruth:
    """Registers each pair by the written scene's truth (each fragment known by its first point)."""

    def __init__(self, clouds, poses, wrong=()):
        self.clouds, self.poses, self.wrong = clouds, poses, set(wrong)

    def prepare_scans(self, clouds):
        from conftest import scan_set

        return scan_set(clouds)

    def register_scan_pairs(self, scans, pairs, batch_size=8, on_pair=None):
        from conftest import scan_set

        clouds = scan_set(scans).clouds
        return self.register_pairs([(clouds[s], clouds[t]) for s, t in pairs], batch_size, on_pair)

    def register_pairs(self, pairs, batch_size=8, on_pair=None):
        from conftest import exact_result

        index = lambda cloud: int(np.argmin([np.abs(c[0] - cloud[0]).sum() for c in self.clouds]))
        results = []
        for src, tgt in pairs:
            s, t = index(src), index(tgt)
            motion = np.linalg.inv(self.poses[t]) @ self.poses[s]
            if (s, t) in self.wrong:  # a quarter turn off
                motion = motion @ np.array([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            wrong = (s, t) in self.wrong  # a wrong result that lays little of its source on the target
            results.append(exact_result(motion, "probably wrong" if wrong else "trusted", 0.2 if wrong else 0.9))
        return results


def test_a_scene_is_scored_from_its_placed_poses_beside_the_pairwise_results(tmp_path, monkeypatch):
    from conftest import write_3dmatch_scene

    from dit_jax import io
    from dit_jax.evaluators import scenes

    rng = np.random.default_rng(4)
    world = rng.normal(size=(300, 3)) * [2.0, 1.0, 0.5]
    poses = write_3dmatch_scene(tmp_path / "room", world, rng, fragments=(0, 1, 2, 3))
    clouds = [io.read(tmp_path / "room" / f"cloud_bin_{k}.ply") for k in range(4)]
    truth = np.stack([poses[k] for k in range(4)])
    # Fragment 3 onto fragment 0 is found probably wrong: the scene still places 3 through 1 and 2.
    registrar = _SceneTruth(clouds, truth, wrong=[(3, 0)])
    from dit_jax.evaluators import scene_baselines

    # A whole-scene baseline that places every fragment right but fragment 2, half a metre off.
    off = np.linalg.inv(truth[0]) @ truth
    off[2, :3, 3] += [0.5, 0.0, 0.0]
    asked = []

    def multiway(clouds, on_pair=None, known=None, on_result=None):  # each pair a second, as logged
        for source, target in [(s, t) for s in range(len(clouds)) for t in range(s + 1, len(clouds))]:
            if (source, target) not in known:
                asked.append((source, target))
                on_result(scene_baselines.MultiwayPair(source, target, off[target], 0.5, np.eye(6), 1.0))
        return off

    monkeypatch.setitem(scene_baselines.SCENE_BASELINES, "open3d_multiway", multiway)
    evaluate = lambda: scenes.evaluate_scenes(  # noqa: E731
        None, tmp_path, str(tmp_path / "out"), progress=False, registrar=registrar, baselines=["open3d_multiway"]
    )
    log = scenes.baseline_log(tmp_path / "out", "open3d_multiway", tmp_path / "room")
    log.parent.mkdir()
    log.write_text(json.dumps(scene_baselines.MultiwayPair(0, 2, off[2], 0.5, np.eye(6), 1.0).to_record()) + '\n{"cut')
    results = evaluate()
    assert len(asked) == 5 and (0, 2) not in asked, "the logged pair is taken as it is"
    lines = log.read_text().splitlines()
    assert len(lines) == 7 and lines[1] == '{"cut', "appended after the cut line, which stays"
    (row,) = results["scenes"]
    assert row["scene"] == "room" and row["placed"] == 4 and row["left_out"] == []
    counts = row["lists"]["3DMatch"]
    assert counts["pairs"] == 6 and counts["scene"] == 6 and counts["pairwise"] == 5
    assert counts["scene_rmse"] == 6 and counts["pairwise_rmse"] == 5
    assert row["position_max"] < 1e-5 and row["rotation_max_deg"] < 1e-3
    assert (row["pairs_registered"], row["rejected"]) == (6, 1) and row["levels"] == {"trusted": 5, "probably wrong": 1}
    table = (tmp_path / "out" / "results.md").read_text()
    assert "| room | 3DMatch | 6 | 6 | 5 | 6 | 5 | 4 of 4 (4) |" in table
    multiway = row["baselines"]["open3d_multiway"]
    assert multiway["lists"]["3DMatch"]["scene"] == 3 and multiway["position_max"] == pytest.approx(0.5)
    assert "| 3 | 0.250 / 0.500 |" in table
    # Its seconds: this run's own, with the logged pairs' as they were logged (the fake takes no time).
    assert 1.0 <= multiway["seconds"] < 2.0 and multiway["pairs_logged_before"] == 1
    again = evaluate()["scenes"][0]["baselines"]["open3d_multiway"]
    assert len(asked) == 5 and again["pairs_logged_before"] == 6 and len(log.read_text().splitlines()) == 7
    assert again["lists"] == multiway["lists"] and 6.0 <= again["seconds"] < 7.0
    assert (tmp_path / "out" / "scene_room.png").stat().st_size > 10_000, "a picture of the scene"
    with pytest.raises(ValueError, match="no 3DMatch scene"):
        scenes.scene_folders(tmp_path / "out")


def test_a_benchmark_pair_the_scene_did_not_register_is_registered_for_the_pairwise_column(tmp_path, monkeypatch):
    from conftest import write_3dmatch_scene

    from dit_jax import io
    from dit_jax.evaluators import scenes
    from dit_jax.scenes import scene

    monkeypatch.setattr(scene, "MAX_ROUNDS", 0)  # the neighbours alone: (4, 0) is none of them
    rng = np.random.default_rng(5)
    poses = write_3dmatch_scene(tmp_path / "room", rng.normal(size=(300, 3)), rng, fragments=(0, 1, 2, 3, 4))
    clouds = [io.read(tmp_path / "room" / f"cloud_bin_{k}.ply") for k in range(5)]
    registrar = _SceneTruth(clouds, np.stack([poses[k] for k in range(5)]))
    (row,) = scenes.evaluate_scenes(None, tmp_path, str(tmp_path / "out"), progress=False, registrar=registrar)[
        "scenes"
    ]
    assert row["pairs_registered"] == 9, "the scene's own pairs"
    assert row["lists"]["3DMatch"] == {"pairs": 10, "scene": 10, "pairwise": 10, "scene_rmse": 10, "pairwise_rmse": 10}
