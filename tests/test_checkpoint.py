import json
import shutil

import jax
import numpy as np
import pytest

from dit_jax import checkpoint, configs, model


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
