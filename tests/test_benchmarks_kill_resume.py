"""benchmarks/kill_resume.py at a small size: killed runs resume without losing a byte, one record per pair."""

import json
import subprocess
import sys

from conftest import ROOT


def test_killed_runs_resume_with_one_record_per_pair_and_nothing_lost():
    done = subprocess.run(
        [sys.executable, "benchmarks/kill_resume.py", "--pairs", "3", "--kills", "1", "--longest", "4"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    record = json.loads(done.stdout.splitlines()[-1])
    assert done.returncode == 0, (record, done.stderr[-2000:])
    assert record["runs_that_lost_bytes"] == 0 and record["one_record_per_pair_after_kills"]
    assert record["one_record_per_pair_with_three_writers"]
