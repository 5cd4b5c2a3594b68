"""tools/readme_tables.py: the README's summary tables, ranked as the README says they are."""

import readme_tables


def _stats(success, within, iso, seconds=0.1):
    return {
        "success": success,
        "rot_iso": iso,
        "rot_mae": iso / 2,
        "seconds_per_pair": seconds,
        "success_curve": {"rotation_thresholds": [1.0, 5.0, 10.0], "ratio": [success, within, 1.0]},
    }


SETTINGS = {
    "independent_clean": {
        "DIT": _stats(0.1, 0.4, 9.0),
        "DIT+ICP": _stats(0.8, 0.9, 3.0),
        "icp": _stats(0.8, 0.9, 4.0),  # ties DIT+ICP in success and within 5: the lower error wins
        "fgr": _stats(0.8, 0.95, 20.0),  # ties in success, more within 5: first
        "fpfh_ransac": _stats(0.5, 0.6, 1.0),  # the lowest error, but the least success of the baselines
    }
}


def test_best_table_ranks_by_success_then_within_5_then_error():
    row = readme_tables.best_table(SETTINGS)[2]
    assert row.startswith("| independent_clean | fgr: 80 % success, 95 % within 5 deg, iso R 20 | DIT+ICP: 80 %")
    assert row.endswith("| 10 % / iso 9 | 80 % / iso 3 | - |")  # no pipeline row in these results


def test_versus_table_shows_the_network_and_the_strongest_baseline():
    rows = readme_tables.versus_table(SETTINGS)[2:]
    assert [r.split(" | ")[1] for r in rows] == ["DIT", "DIT+ICP", "fgr"]


def test_changes_name_both_rows_before_and_after():
    before = {"independent_clean": {"DIT": _stats(0.05, 0.3, 10.0), "DIT+ICP": _stats(0.8, 0.9, 3.0)}}
    (line,) = readme_tables.changes(SETTINGS, before)
    assert "DIT success 5 % -> 10 %, within 5 30 % -> 40 %" in line
    assert "DIT+ICP success 80 % -> 80 %" in line


def test_verdict_table_counts_flagged_failures_and_right_trusted_results(tmp_path):
    import json

    verdict = {"failures": 4, "failures_caught": 0.75, "passed": 10, "passed_right": 0.9}
    none_failed = {"failures": 0, "failures_caught": float("nan"), "passed": 5, "passed_right": 1.0}
    (tmp_path / "mn").mkdir()
    (tmp_path / "mn" / "results.json").write_text(
        json.dumps(
            {
                "settings": {
                    "independent_clean": {
                        "DIT": {"pairs": 14, "verdict": none_failed},
                        "DIT+ICP": {"pairs": 14, "verdict": verdict},
                    }
                }
            }
        )
    )
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "results.json").write_text(
        json.dumps(
            {
                "scans": "/data/dragon/",
                "pair_sets": {
                    "skip1": {
                        "DIT": {"summary": {"pairs": 15, "verdict": verdict}},
                        "DIT+ICP": {"summary": {"pairs": 15}},
                    }
                },
            }
        )
    )
    rows = readme_tables.verdict_table([str(tmp_path / "scans"), str(tmp_path / "mn")])[2:]
    assert rows == [
        "| dragon skip1 (15 pairs) | 3 of 4 | 9 of 10 | - | - | - | - |",
        "| mn independent_clean (14 pairs) | - | 5 of 5 | 3 of 4 | 9 of 10 | - | - |",
    ]
