import json
import shutil

import jax
import numpy as np
import pytest

from dit_jax.network import checkpoint, configs, model


def test_save_restore_round_trip(tmp_path):
    config = configs.tiny("low_noise_partial")
    params = model.init(jax.random.key(0), config)
    checkpoint.save(tmp_path / "ck", params, config)
    restored, restored_config = checkpoint.restore(tmp_path / "ck")
    assert restored_config == config
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), params, restored)


def test_existing_directory_is_not_overwritten(tmp_path):
    config = configs.tiny()
    params = model.init(jax.random.key(0), config)
    checkpoint.save(tmp_path / "ck", params, config)
    with pytest.raises(checkpoint.CheckpointError, match="already exists"):
        checkpoint.save(tmp_path / "ck", params, config)


def test_missing_damaged_and_mismatched_checkpoints_raise_clear_errors(tmp_path):
    with pytest.raises(checkpoint.CheckpointError, match="no such checkpoint directory"):
        checkpoint.restore(tmp_path / "nothing")
    config = configs.tiny()
    checkpoint.save(tmp_path / "ck", model.init(jax.random.key(0), config), config)
    # A config whose shapes differ from the stored params.
    bad = tmp_path / "mismatch"
    shutil.copytree(tmp_path / "ck", bad)
    meta_file = next((bad / "config").glob("*"))
    meta = json.loads(meta_file.read_text())
    meta["dit_config"]["n_blocks"] = 2
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(checkpoint.CheckpointError, match="params do not restore for the stored config"):
        checkpoint.restore(bad)
    shutil.rmtree(tmp_path / "ck" / "params")
    with pytest.raises(checkpoint.CheckpointError, match="params do not restore"):
        checkpoint.restore(tmp_path / "ck")


def test_update_extra_adds_to_the_record_and_leaves_the_params_files_alone(tmp_path):
    """A newly chosen setting (the verdict's thresholds) goes into a shipped checkpoint's record without a new
    copy of its weights: only the record's file changes, and the params restore as before."""
    config = configs.tiny()
    params = model.init(jax.random.PRNGKey(0), config)
    path = checkpoint.save(tmp_path / "m", params, config, extra={"step": 7})
    files = sorted(p for p in (tmp_path / "m").rglob("*") if p.is_file())
    before = {p: p.read_bytes() for p in files}
    checkpoint.update_extra(path, {"verdict_max_disagreement": {"none": 3.0, "icp": 6.0}})
    assert checkpoint.read_extra(path) == {"step": 7, "verdict_max_disagreement": {"none": 3.0, "icp": 6.0}}
    changed = [p.relative_to(tmp_path / "m").as_posix() for p in files if p.read_bytes() != before[p]]
    assert changed == ["config/metadata"]
    assert sorted(p for p in (tmp_path / "m").rglob("*") if p.is_file()) == files
    restored, restored_config = checkpoint.restore(path)
    assert restored_config == config
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(restored)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(checkpoint.CheckpointError, match="no such checkpoint"):
        checkpoint.update_extra(tmp_path / "absent", {})


def test_update_config_changes_inference_fields_and_refuses_shape_changes(tmp_path):
    """An inference setting chosen after training (more iterations) goes into the stored config in place;
    the params restore under it, the record is kept, and a field that would reshape the params is refused."""
    config = configs.tiny()
    params = model.init(jax.random.PRNGKey(0), config)
    path = checkpoint.save(tmp_path / "m", params, config, extra={"step": 7})
    new = checkpoint.update_config(path, {"n_iters": config.n_iters + 2, "gmcce_min_keep": 0.3})
    restored, restored_config = checkpoint.restore(path)
    assert restored_config == new == config.replace(n_iters=config.n_iters + 2, gmcce_min_keep=0.3)
    assert checkpoint.read_extra(path) == {"step": 7}
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(restored)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(checkpoint.CheckpointError, match="shapes"):
        checkpoint.update_config(path, {"n_blocks": config.n_blocks + 1})
    with pytest.raises(checkpoint.CheckpointError, match="cannot apply"):
        checkpoint.update_config(path, {"no_such_field": 1})
    assert checkpoint.read_config(path) == new, "a refused change leaves the config as it was"


def test_restore_keeps_a_plain_copy_in_the_cache_and_reads_it_without_orbax(tmp_path, monkeypatch):
    """With the compilation cache on, the first restore writes the params' plain copy and later ones read it
    (orbax's restore is not called), bit for bit; a damaged copy is restored through orbax again and
    rewritten; another checkpoint's params at the same path get a copy of their own."""
    from dit_jax.network import compile_cache

    monkeypatch.setitem(compile_cache._enabled, "directory", str(tmp_path / "cache"))
    config = configs.tiny()
    params = model.init(jax.random.key(0), config)
    checkpoint.save(tmp_path / "ck", params, config)
    first, _ = checkpoint.restore(tmp_path / "ck")
    (copy,) = (tmp_path / "cache" / "params").iterdir()

    def no_orbax(path):
        raise AssertionError("restored through orbax")

    with monkeypatch.context() as patch:
        patch.setattr(checkpoint, "_restore_params", no_orbax)
        again, _ = checkpoint.restore(tmp_path / "ck")
    for a, b, c in zip(jax.tree.leaves(params), jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    assert jax.tree.structure(params) == jax.tree.structure(again)

    whole = copy.read_bytes()
    for damage in (b"damaged", whole[: len(whole) // 2]):  # not a zip file; a zip file cut short
        copy.write_bytes(damage)
        repaired, _ = checkpoint.restore(tmp_path / "ck")
        np.testing.assert_array_equal(np.asarray(jax.tree.leaves(repaired)[0]), np.asarray(jax.tree.leaves(params)[0]))
        assert copy.read_bytes() != damage and len(np.load(copy).files) == len(jax.tree.leaves(params))

    other = model.init(jax.random.key(1), config)
    checkpoint.save(tmp_path / "ck", other, config, overwrite=True)
    restored, _ = checkpoint.restore(tmp_path / "ck")
    np.testing.assert_array_equal(np.asarray(jax.tree.leaves(restored)[0]), np.asarray(jax.tree.leaves(other)[0]))
    assert len(list((tmp_path / "cache" / "params").iterdir())) == 2
