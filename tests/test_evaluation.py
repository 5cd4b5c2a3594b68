import json
import os
import sys

import jax
import pytest

from dit_jax import checkpoint, configs, evaluation, model


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "model"
    config = configs.tiny()
    checkpoint.save(path, model.init(jax.random.key(0), config), config, extra={"n_points": 128})
    return str(path)


def test_evaluate_end_to_end_writes_tables_json_and_plots(tiny_checkpoint, tmp_path):
    names = ["icp"] if __import__("dit_jax.baselines").baselines.available() else []
    out = tmp_path / "eval"
    results = evaluation.evaluate(tiny_checkpoint, str(out), settings=("clean", "high_noise_partial"),
                                  max_pairs=4, baselines=names, prepared_dir=str(tmp_path / "p"), progress=False)
    assert sorted(os.listdir(out)) == ["registrations.png", "results.json", "results.md", "success_ratio.png"]
    saved = json.loads((out / "results.json").read_text())
    assert saved["n_points"] == 128, "the training run's point count is the default"
    for setting in ("clean", "high_noise_partial"):
        dit = saved["settings"][setting]["DIT"]
        assert dit["pairs"] == 4 and dit["seconds_per_pair"] > 0 and dit["chamfer"] >= 0
        assert saved["setting_info"][setting]["gmcce_threshold"] == configs.GMCCE_THRESHOLDS[setting]
        assert sum(c["pairs"] for c in dit["by_category"].values()) == 4
        assert set(saved["settings"][setting]) == {"DIT", *names}
    assert "| DIT |" in (out / "results.md").read_text()
    assert (out / "success_ratio.png").stat().st_size > 10_000


def test_evaluate_cli_reports_a_missing_checkpoint(tmp_path, capsys):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import evaluate

    assert evaluate.main(["--checkpoint", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    assert "no such checkpoint directory" in capsys.readouterr().err


def test_evaluate_cli_uses_the_shipped_weights_by_default(tmp_path, capsys):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import evaluate
    from dit_jax import registration

    assert evaluate.main(["--max-pairs", "2", "--out", str(tmp_path), "--no-progress"]) == 0
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["checkpoint"] == os.path.abspath(registration.shipped_weights())
    extra = checkpoint.read_extra(registration.shipped_weights())
    assert saved["n_points"] == (extra.get("inference_points") or extra.get("n_points") or 1000)
