"""benchmarks/gpu_check.py in its smoke mode: every part runs, on the CPU, into one JSON record."""

import json
import subprocess
import sys

from conftest import ROOT


def test_the_gpu_check_runs_every_part_in_smoke_mode(tmp_path, reference_file):
    out = tmp_path / "check"
    done = subprocess.run(
        [sys.executable, "benchmarks/gpu_check.py", "--smoke", "--out", str(out), "--reference", str(reference_file)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    record = json.loads((out / "gpu_check.json").read_text())
    assert record["smoke"] is True and record["platform"] == "cpu"
    assert record["reference"]["passed"] == record["reference"]["checks"] > 20
    speed = record["inference"]["speed"]
    assert [r["batch"] for r in speed] == [1, 2] and all(r["seconds_per_pair"] > 0 for r in speed)
    assert [r["n_points"] for r in record["inference"]["memory"]] == [64, 96]
    steps = record["train_step"]
    assert [s["precision"] for s in steps] == ["highest", "bfloat16"]
    assert all(s["step_s"] > 0 and s["pairs_per_s"] > 0 for s in steps)
    training = record["training"]
    assert training["step"] == training["total_steps"] == 2
    assert training["val"]["network_rotation_error"] >= 0
    assert (out / "training" / "model").is_dir()
    assert (out / "xla_cache").is_dir()
    estimator = record["estimator"]["buckets"]
    assert [b["matches"] for b in estimator] == [512] and estimator[0]["error_deg"] < 0.5


def test_the_gpu_check_refuses_an_unknown_part(tmp_path):
    done = subprocess.run(
        [sys.executable, "benchmarks/gpu_check.py", "--out", str(tmp_path), "--only", "everything"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "invalid choice" in done.stderr


def test_the_reference_part_without_its_file_is_skipped_with_a_reason(tmp_path):
    done = subprocess.run(
        [sys.executable, "benchmarks/gpu_check.py", "--smoke", "--out", str(tmp_path), "--only", "reference"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads((tmp_path / "gpu_check.json").read_text())["reference"] == "skipped: no --reference file"
