"""The shipping rule's verdict and its resampled copy of the validation pairs."""

import numpy as np
import shipping_rule


def _rows(clean, *hard):
    return {"clean": {"within_5": clean}, **{s: {"within_5": v} for s, v in zip(shipping_rule.HARD, hard)}}


def test_a_candidate_ships_only_where_every_sampling_passes():
    shipped = {"own": _rows(1.0, 0.1, 0.3, 0.2, 0.1), "varied": _rows(1.0, 0.1, 0.3, 0.2, 0.1)}
    better = _rows(1.0, 0.2, 0.4, 0.2, 0.15)  # +0.25 together, no loss
    assert shipping_rule.verdict(shipped, {"own": better, "varied": better})["ships"]
    # the same gain with one setting losing more than LOSS
    lossy = _rows(1.0, 0.5, 0.4, 0.05, 0.1)
    out = shipping_rule.verdict(shipped, {"own": better, "varied": lossy})
    assert out["own"]["passes"] and not out["varied"]["passes"] and not out["ships"]
    assert np.isclose(out["varied"]["worst_hard_loss"], 0.15)
    # a clean pair lost
    out = shipping_rule.verdict(shipped, {"own": _rows(0.97, 0.3, 0.4, 0.2, 0.15), "varied": better})
    assert out["own"]["clean_loss"] > 0 and not out["ships"]
    # too small a gain
    small = _rows(1.0, 0.15, 0.35, 0.2, 0.1)
    assert not shipping_rule.verdict(shipped, {"own": small, "varied": small})["ships"]


def test_the_varied_copy_resamples_every_cloud_and_keeps_correspondences_true():
    rng = np.random.default_rng(0)
    tgt = rng.normal(size=(3, 50, 3)).astype(np.float32)
    perm = np.stack([rng.permutation(50) for _ in range(3)])
    src = np.take_along_axis(tgt, perm[..., None], axis=1)  # src[i] = tgt[perm[i]]
    batch = {"src": src, "tgt": tgt, "R": np.tile(np.eye(3), (3, 1, 1)), "correspondence": perm}
    out = shipping_rule.resampled(batch, 384)
    assert out["src"].shape == out["tgt"].shape == (3, 40, 3)  # 80 % of the smallest cloud
    for s, t, c in zip(out["src"], out["tgt"], out["correspondence"]):
        kept = c >= 0
        np.testing.assert_array_equal(s[kept], t[c[kept]])


def test_both_checkpoints_run_the_shipped_weights_model_options():
    """A candidate exported from training stores the authors' GMCCE defaults in its config; the rule must
    run it with the options the shipped weights run under, not those."""
    from dit_jax.network import configs
    from dit_jax.pipeline import registration

    shipped_config = configs.DITConfig().replace(gmcce_threshold=0.9, gmcce_min_keep=0.3, guard_iterations=True)
    shipped = registration.Registrar({}, shipped_config)
    settings = shipping_rule.inference_settings(shipped)
    candidate = registration.Registrar({}, configs.DITConfig(), settings)
    assert candidate.config == shipped.config
    assert settings.refine == "none" and not settings.rotation_search


def test_shipped_records_name_the_modelnet40_folder_not_the_machines_path():
    from ship_weights import portable

    record = {
        "command": "python train.py --config.data_dir=../shared/data/mn40 --unseen",
        "train_config": {"data_dir": "../shared/data/mn40", "seed": 3},
        "trained_from": {"data": ["../shared/data/mn40/"]},
    }
    assert portable(record, "../shared/data/mn40") == {
        "command": "python train.py --config.data_dir=$MODELNET40 --unseen",
        "train_config": {"data_dir": "$MODELNET40", "seed": 3},
        "trained_from": {"data": ["$MODELNET40/"]},
    }
    assert portable(record, None) == record
