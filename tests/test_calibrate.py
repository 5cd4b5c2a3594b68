"""tools/calibrate.py: the rule that sets the shipped thresholds, made again from kept evidence, and
what it writes into a checkpoint's inference settings."""

import calibrate
import jax
import numpy as np

from dit_jax.network import checkpoint, configs, model
from dit_jax.pipeline import registration


def _evidence(errors, agreement, settings):
    return {"setting": list(settings), "rot_err": list(errors), "agreement": list(agreement)}


def test_largest_threshold_keeps_95_percent_of_the_trusted_results_right():
    # 20 right results agreeing within 0.4 deg, one failure at 0.9, 5 right ones at 1.4, 3 failures at 1.9.
    agreement = np.r_[np.full(20, 0.4), 0.9, np.full(5, 1.4), np.full(3, 1.9)]
    errors = np.r_[np.full(20, 1.0), 40.0, np.full(5, 1.0), np.full(3, 30.0)]
    assert calibrate.largest_threshold(errors, agreement) == 1.5  # 25 of 26 right; at 2.0, 25 of 29
    errors[20:26] = 30.0  # from 0.9 on, every result is wrong
    assert calibrate.largest_threshold(errors, agreement) == 1.0  # 20 of 21 right; at 1.5, 20 of 26
    assert calibrate.largest_threshold(np.full(4, 30.0), np.full(4, 0.1)) is None


def test_choice_pools_the_settings_that_share_no_point_and_falls_back_to_trusting_none_of_the_pool():
    # Shared-point pairs: all right and agreeing; independent pairs: the network alone never reaches 95 %.
    settings = ["clean"] * 10 + ["independent_clean"] * 10
    icp = _evidence([0.1] * 10 + [1.0] * 9 + [50.0], [0.01] * 10 + [0.3] * 9 + [2.5], settings)
    alone = _evidence([0.1] * 10 + [1.0, 30.0] * 5, [0.01] * 10 + [0.3] * 10, settings)
    report = calibrate.choose_from_evidence({"none": alone, "icp": icp}, ["independent_clean"])
    assert report["verdict_max_disagreement"] == {"none": 0.25, "icp": 2.0}
    assert report["verdict_fallback"] == ["none"]
    on_clean = report["verdict_agreement_on_validation"]["none"]["clean"]
    assert on_clean["passed"] == 10 and on_clean["passed_right"] == 1.0  # near-exact agreement is still trusted
    assert report["verdict_agreement_on_validation"]["icp"]["pool"]["failures_caught"] == 1.0


def test_fallback_takes_the_most_precise_threshold_with_enough_trusted_results():
    # No threshold reaches 95 %: 0.25 trusts 10 results, 8 right; 0.5 trusts 20, 18 right; 1.0 trusts 30, 25 right.
    agreement = np.r_[np.full(10, 0.2), np.full(10, 0.4), np.full(10, 0.9), np.full(10, 20.0)]
    errors = np.r_[np.full(8, 1.0), 30.0, 30.0, np.full(10, 1.0), np.full(7, 1.0), np.full(3, 30.0), np.full(10, 30.0)]
    report = calibrate.choose_from_evidence(
        {"icp": _evidence(errors, agreement, ["independent_clean"] * 40)}, ["independent_clean"]
    )
    assert report["verdict_max_disagreement"] == {"icp": 0.5} and report["verdict_fallback"] == ["icp"]
    # A threshold trusting fewer results than a band needs is not taken, however right they are.
    errors[8:10] = 1.0
    agreement[:10] = np.r_[np.full(5, 0.2), np.full(5, 0.4)]
    agreement[10:20] = 0.9
    errors[10:13] = 30.0
    report = calibrate.choose_from_evidence(
        {"icp": _evidence(errors, agreement, ["independent_clean"] * 40)}, ["independent_clean"]
    )
    assert report["verdict_max_disagreement"] == {"icp": 0.5}  # 10 trusted, all right; 0.25 trusts only 5
    # Where every threshold trusts a few but fewer than a band needs, the smallest.
    assert calibrate.fallback_threshold([{"passed": 3, "passed_right": 1.0}] * 11) == 0.25


def test_record_writes_the_thresholds_into_the_inference_settings(tmp_path):
    config = configs.tiny()
    path = checkpoint.save(
        tmp_path / "m",
        model.init(jax.random.key(0), config),
        config,
        extra={"note": "Trained somewhere.", "inference_settings": {"max_disagreement_network": 1.0, "n_points": 128}},
    )
    before = {p.name: p.read_bytes() for p in (tmp_path / "m").rglob("*") if p.is_file() and "config" not in p.parts}
    report = {
        "verdict_max_disagreement": {"none": 0.25, "icp": 0.5},
        "verdict_pool": ["independent_clean"],
        "pairs_per_setting": 128,
        "verdict_fallback": ["none"],
    }
    calibrate.record(str(path), report)
    extra = checkpoint.read_extra(path)
    settings = registration.settings_from_extra(extra)
    assert (settings.max_disagreement_network, settings.max_disagreement_icp) == (0.25, 0.5)
    assert settings.n_points == 128, "settings the choice does not touch are kept"
    assert extra["calibration"]["verdict_fallback"] == ["none"] and extra["note"] == "Trained somewhere."
    assert registration.load(path).settings == settings
    after = {p.name: p.read_bytes() for p in (tmp_path / "m").rglob("*") if p.is_file() and "config" not in p.parts}
    assert after == before, "the params' files are untouched"


def test_agreement_bands_count_each_band_and_agree_with_the_recorded_curve(tmp_path):
    """The bands quoted beside a verdict: per agreement band, how many validation results and how many right;
    rebuilt from a record's cumulative precision curve (records made before bands were kept), the same."""
    rng = np.random.default_rng(0)
    agreement = rng.exponential(3.0, 400)
    errors = np.where(rng.random(400) < np.exp(-agreement / 4), 1.0, 30.0)  # the closer, the likelier right
    settings = ["independent_clean"] * 400
    report = calibrate.choose_from_evidence({"icp": _evidence(errors, agreement, settings)}, ["independent_clean"])
    bands = report["verdict_agreement_bands"]["icp"]
    assert [b[0] for b in bands] == [*calibrate.AGREEMENT_GRID, None]
    assert sum(b[1] for b in bands) == 400 and sum(b[2] for b in bands) == int((errors <= 5).sum())
    assert bands[2] == [
        1.0,
        int(((agreement > 0.5) & (agreement <= 1)).sum()),
        int(((agreement > 0.5) & (agreement <= 1) & (errors <= 5)).sum()),
    ]
    config = configs.tiny()
    path = checkpoint.save(tmp_path / "m", model.init(jax.random.key(0), config), config)
    report["pairs_per_setting"] = 400
    calibrate.record(str(path), report)
    stored = registration.load(path).settings.agreement_bands_icp
    assert stored == tuple(tuple(band) for band in bands)
