"""tools/network_targets.py: the test figures a training stage is quoted by, for a candidate beside the
shipped weights, both under the shipped weights' inference settings."""

import json

import network_targets
import pytest
from conftest import MODELNET_DIR, ROOT


def test_the_shipped_weights_as_candidate_score_as_the_shipped_weights(tmp_path, prepared_dir, dragon_dir):
    if not MODELNET_DIR.exists():
        pytest.skip(f"ModelNet40 is not here ({MODELNET_DIR}); it ships with ../shared")
    out = tmp_path / "targets.json"
    network_targets.main(
        [
            str(ROOT / "dit_jax" / "network" / "weights" / "dit-cpu-modelnet40"),
            "--data-dir", str(MODELNET_DIR),
            "--dragon", str(dragon_dir),
            "--prepared-dir", str(prepared_dir),
            "--pairs", "1",
            "--dragon-pairs", "1",
            "--out", str(out),
        ]
    )  # fmt: skip
    report = json.loads(out.read_text())
    assert report["candidate"] == report["shipped"]
    assert report["shipped"]["independent_clean_unseen"]["pairs"] == 1
    assert report["shipped"]["dragon_neighbours"]["pairs"] == 1
    # The dragon's first neighbouring pair: the network alone lands within 5 degrees (docs/eval_stanford_dragon).
    assert report["shipped"]["dragon_neighbours"]["within_5"] == 1
