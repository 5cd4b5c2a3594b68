import json

import jax
import numpy as np

from dit_jax.network import configs, convert, model, reference_check


def test_authors_reference_file_passes(reference_file, capsys):
    assert reference_check.main([str(reference_file), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["passed"] and not report["failed"] and not report["unchecked"]
    assert report["max_abs_error"]["predict_R"] <= reference_check.POSE_TOL
    assert report["agreement"]["head_gmcce_weight"] >= reference_check.MIN_AGREEMENT


def _file_for(config, authors_config, n, m, seed):
    """A check file in the authors' format for another config, with the activations dit-jax computes."""
    rng = np.random.default_rng(seed)
    params = model.init(jax.random.key(seed), config)
    data = {
        "config": np.array(repr(authors_config)),
        "src": rng.uniform(-1, 1, (n, 3)).astype(np.float32),
        "tgt": rng.uniform(-1, 1, (m, 3)).astype(np.float32),
    }
    data.update({f"param/{k}": v for k, v in convert.to_torch_state_dict(params, config).items()})
    for i in range(config.n_iters):  # the checker reads the iteration count off these names
        data[f"iter{i}_R"] = np.eye(3, dtype=np.float32)[None]
    data.update(reference_check.compute(data))
    return data


def test_other_widths_depths_and_point_counts_are_checked(tmp_path, capsys):
    authors = {
        "n_emb_dims": 64,
        "token_dim": 8,
        "n_blocks": 3,
        "n_ff_dims": 96,
        "n_heads": 2,
        "k": 12,
        "gmcce_k": 6,
        "gmcce_sharpness": 30.0,
        "gmcce_threshold": 0.9,
        "temp_factor": 100.0,
        "n_points": 96,
    }
    config = configs.from_authors(authors, n_iters=3)
    data = _file_for(config, authors, n=96, m=80, seed=1)
    assert data["scores"].shape == (1, 96, 80) and data["pft_tgt"].shape == (1, 64, 80)
    good = tmp_path / "good.npz"
    np.savez(good, **data)
    assert reference_check.main([str(good)]) == 0
    assert "PASSED: 28/28 checks" in capsys.readouterr().out

    # One weight matrix off by noise of 1e-3 must be caught. (A uniform shift would not be: the decoder's
    # final norm removes it.)
    name = "param/attention.model.decoder.layers.2.feed_forward.w_2.weight"
    data[name] = data[name] + np.random.default_rng(0).normal(0, 1e-3, data[name].shape).astype(np.float32)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **data)
    assert reference_check.main([str(bad), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert not report["passed"] and "pft_src" in report["failed"]


def test_unreadable_file_exits_2(tmp_path, capsys):
    path = tmp_path / "broken.npz"
    path.write_bytes(b"nope")
    assert reference_check.main([str(path)]) == 2
    assert "broken.npz" in capsys.readouterr().err


def test_command_line_exit_status(reference_file):
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "dit_jax.network.reference_check", str(reference_file)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "PASSED: 26/26 checks" in done.stdout
