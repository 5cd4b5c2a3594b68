"""The registration pipeline's settings and stages that need no network: one typed record of every inference
setting, its round trip through a checkpoint, and the stages' typed records."""

import dataclasses
import re

import jax
import numpy as np
import pytest

from dit_jax.network import checkpoint, configs, model
from dit_jax.pipeline import network_stage, refinement, registration, stages, verdict
from dit_jax.pipeline.sampling import normalise, to_caller_units
from dit_jax.pipeline.settings import DENSE_POINTS, SCAN_POINTS, InferenceSettings, refinement_for


def test_settings_are_frozen_validated_and_round_trip_through_a_dict():
    settings = InferenceSettings(n_points=512, refine="none", agreement_bands_icp=[[1.0, 20, 19], [None, 5, 1]])
    assert settings.agreement_bands_icp == ((1.0, 20, 19), (None, 5, 1)), "bands are stored immutable"
    assert InferenceSettings.from_dict(settings.to_dict()) == settings
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.n_points = 3
    for bad, fragment in (
        ({"refine": "ndt"}, "refine must be one of"),
        ({"centring": "middle"}, "centring"),
        ({"verdict_rule": "vote"}, "verdict_rule"),
        ({"precision": "half"}, "precision"),
        ({"n_iters": 0}, "n_iters"),
        ({"n_points": 0}, "positive"),
    ):
        with pytest.raises(ValueError, match=fragment):
            InferenceSettings(**bad)
    with pytest.raises(ValueError, match="unknown InferenceSettings fields: bogus"):
        InferenceSettings.from_dict({"bogus": 1})


def test_settings_override_only_the_model_options_they_set():
    config = configs.tiny()
    assert InferenceSettings().model_config(config) == config
    changed = InferenceSettings(n_iters=5, gmcce_threshold=0.5, precision="tf32").model_config(config)
    assert (changed.n_iters, changed.gmcce_threshold, changed.precision) == (5, 0.5, "tf32")
    assert (
        changed.replace(n_iters=config.n_iters, gmcce_threshold=config.gmcce_threshold, precision=config.precision)
        == config
    )


def test_a_checkpoint_stores_its_settings_and_load_changes_them(tmp_path):
    config = configs.tiny()
    stored = InferenceSettings(n_points=128, max_disagreement_icp=2.0, min_fitness=0.8)
    path = checkpoint.save(
        tmp_path / "m",
        model.init(jax.random.key(0), config),
        config,
        extra={registration.SETTINGS_KEY: stored.to_dict()},
    )
    assert registration.load(path).settings == stored
    assert registration.load(path, refine="none").settings == stored.replace(refine="none")
    bare = checkpoint.save(tmp_path / "bare", model.init(jax.random.key(0), config), config)
    assert registration.load(bare).settings == InferenceSettings(), "defaults live in one place"


def test_auto_refines_scans_by_gicp_and_sparse_clouds_by_icp():
    dense = DENSE_POINTS
    assert refinement_for("auto", dense, dense) == "gicp"
    assert refinement_for("auto", dense, dense - 1) == "icp"  # both clouds must be dense
    for method in ("icp", "gicp", "none"):
        assert refinement_for(method, 10, 10 * dense) == method
    assert InferenceSettings(refine="auto").refinement_for(1024, 1024) == "icp"


def test_the_features_run_first_on_scans_unless_told_otherwise():
    """Scans (3DMatch's smallest fragments included) run them; ModelNet's 1,024-point shapes do not."""
    scan, dense = SCAN_POINTS, DENSE_POINTS
    auto = InferenceSettings(feature_candidate="auto")
    assert auto.runs_feature_candidate(2051, 2051) and auto.runs_feature_candidate(scan, scan)
    assert not auto.runs_feature_candidate(scan - 1, dense) and not auto.runs_feature_candidate(1024, 10 * dense)
    assert InferenceSettings(feature_candidate="on").runs_feature_candidate(100, 100)
    assert not InferenceSettings(feature_candidate="off").runs_feature_candidate(dense, dense)
    # Settings stored as a bool before "auto" read as "on" and "off".
    assert InferenceSettings(feature_candidate=True).feature_candidate == "on"
    assert InferenceSettings.from_dict({"feature_candidate": False}).feature_candidate == "off"
    with pytest.raises(ValueError, match="feature_candidate"):
        InferenceSettings(feature_candidate="sometimes")


def test_normalise_keeps_far_apart_clouds_each_on_its_own_centre():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(100, 3))
    near, far = src + 0.5, src + 1e4
    src_n, tgt_n, src_centre, tgt_centre, scale = normalise(src, near, "auto")
    np.testing.assert_allclose(src_centre, tgt_centre)  # a few radii apart: one shared centre
    assert max(np.linalg.norm(src_n, axis=1).max(), np.linalg.norm(tgt_n, axis=1).max()) == pytest.approx(1.0)
    _, tgt_n, src_centre, tgt_centre, _ = normalise(src, far, "auto")
    np.testing.assert_allclose(tgt_centre - src_centre, [1e4] * 3, atol=1e-6)
    assert np.abs(tgt_n.mean(axis=0)).max() < 1e-9
    rotation = np.eye(3)
    # A motion found between the normalised clouds maps back into the caller's frame.
    assert np.allclose(to_caller_units(rotation, np.zeros(3), src_centre, tgt_centre, 2.0), tgt_centre - src_centre)


def test_the_stages_pass_typed_records_not_dicts_or_tuples():
    """Every stage function takes and returns records (:class:`stages.Pair`, ``PairEstimate``, ``Motion``,
    ``Refined``, ``Verdict``, ``Result``) or arrays; a dict or a bare tuple between them would hide what flows."""
    import inspect

    functions = [
        stages.by_features,
        stages.sampled,
        stages.estimated,
        stages.network_result,
        stages.features_result,
        stages.landing,
        network_stage.estimate_pairs,
        refinement.refine_pair,
        refinement.fitness,
        verdict.judge,
        verdict.judge_features,
    ]
    for stage in functions:
        signature = inspect.signature(stage)
        # ``params`` is the network's weights (Flax's pytree), handed through untouched
        parameters = [p for name, p in signature.parameters.items() if name != "params"]
        annotations = [p.annotation for p in parameters] + [signature.return_annotation]
        for annotation in annotations:
            assert annotation is not inspect.Parameter.empty, f"{stage.__name__}: every parameter is annotated"
            words = re.findall(r"[A-Za-z_]+", str(annotation))
            assert "dict" not in words and "tuple" not in words, f"{stage.__name__}: {annotation}"


def test_register_pairs_reads_as_its_stages():
    import inspect

    source = inspect.getsource(stages.register_pairs)
    assert len(source.splitlines()) <= 40
    positions = [
        source.index(f"{name}(") for name in ("check_pair", "by_features", "sampled", "estimated", "network_result")
    ]
    assert positions == sorted(positions), "the stages run in their order"


def test_the_pairs_of_one_set_of_scans_compute_each_scan_s_features_once(monkeypatch):
    """:func:`stages.register_scan_pairs` builds each scan's features once however many pairs it joins, and
    each pair's result is the one :func:`stages.register_pairs` gives it (the scans share a spacing)."""
    pytest.importorskip("open3d")
    from dit_jax.features import keypoints

    rng = np.random.default_rng(0)
    d = rng.normal(size=(3 * SCAN_POINTS, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = d * (1 + 0.3 * np.sin(6 * d[:, :1]) * np.cos(5 * d[:, 1:2]) + 0.1 * d[:, 2:] ** 2)
    turns = [np.eye(3), *(np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(2))]
    scans = [surface @ (turn * np.sign(np.linalg.det(turn))).T + k for k, turn in enumerate(turns)]
    built = []
    original = keypoints.Cloud

    class Counted(original):
        def __init__(self, *args, **kwargs):
            built.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(keypoints, "Cloud", Counted)
    registrar = registration.load(viewpoint="none")
    pairs = [(1, 0), (2, 0), (2, 1)]
    together = registrar.register_scan_pairs(scans, pairs)
    assert len(built) == 3
    alone = registrar.register_pairs([(scans[s], scans[t]) for s, t in pairs])
    assert len(built) == 3 + 2 * len(pairs)
    for mine, theirs in zip(together, alone):
        assert mine.candidate == "features" and mine.level == theirs.level
        np.testing.assert_allclose(mine.matrix, theirs.matrix, atol=1e-9)
