import jax
import numpy as np
import pytest
from conftest import TEST_DATA

from dit_jax.network import checkpoint, configs, convert, model, torch_pickle


def _equal_trees(a, b):
    return jax.tree.all(jax.tree.map(lambda x, y: bool(np.array_equal(np.asarray(x), np.asarray(y))), a, b))


def test_round_trip_through_the_authors_names():
    config = configs.tiny().replace(n_blocks=3, n_heads=2)
    # Distinct random values in the network's shapes (a swapped or untransposed weight shows), without
    # compiling this config's initialisation.
    rng = np.random.default_rng(1)
    shapes = jax.eval_shape(lambda: model.init(jax.random.key(1), config))
    params = jax.tree.map(lambda a: rng.standard_normal(a.shape).astype(a.dtype), shapes)
    state_dict = convert.to_torch_state_dict(params, config)
    assert state_dict["attention.model.decoder.layers.2.src_attn.linears.3.weight"].shape == (32, 32)
    assert _equal_trees(convert.from_torch_state_dict(state_dict, config), params)


def test_reference_file_weights_convert_and_unused_ones_are_dropped(reference_data):
    config = configs.from_authors(str(reference_data["config"]))
    sd = {k[len("param/") :]: v for k, v in reference_data.items() if k.startswith("param/")}
    params = convert.from_torch_state_dict(sd, config)
    # Linear weights are transposed: PyTorch's (out, in) becomes Flax's (in, out).
    np.testing.assert_array_equal(params["positional_encoding"]["fc0"]["kernel"], sd["Position_encoding.PE.0.weight"].T)
    assert "project" not in params["pse"]
    assert convert.infer_config(sd) == config.replace(gmcce_threshold=configs.DITConfig().gmcce_threshold)


def test_mismatched_state_dict_names_each_problem():
    config = configs.tiny()
    sd = convert.to_torch_state_dict(model.init(jax.random.key(0), config), config)
    sd["emb_nn.norm.weight"] = np.zeros(7, np.float32)
    del sd["SE_Block.fc.2.weight"]
    sd["mystery.weight"] = np.zeros(3, np.float32)
    with pytest.raises(convert.ConversionError) as err:
        convert.from_torch_state_dict(sd, config)
    message = str(err.value)
    assert "unknown tensors: mystery.weight" in message
    assert "missing for this config: se/fc2/kernel" in message
    assert "pse/norm/scale: shape (7,), config needs (32,)" in message


def test_pth_written_by_pytorch_reads_without_pytorch():
    state = convert.load_pth(str(TEST_DATA / "tiny_state_dict.pth"))
    with np.load(TEST_DATA / "tiny_state_dict.npz") as expected:
        assert set(state) == {"module." + k for k in expected.files}
        for name in expected.files:
            np.testing.assert_array_equal(state["module." + name], expected[name])


def test_pth_reader_refuses_code_in_the_pickle(tmp_path):
    import pickle
    import zipfile

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "evil.pth"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", pickle.dumps({"x": Evil()}))
    with pytest.raises(torch_pickle.UnsupportedFile, match="refusing pickled global builtins.print"):
        torch_pickle.load(str(path))


def test_convert_command_writes_a_restorable_checkpoint(tmp_path, capsys):
    out = tmp_path / "ckpt"
    assert convert.main([str(TEST_DATA / "tiny_state_dict.pth"), str(out), "--setting", "high_noise_partial"]) == 0
    params, config = checkpoint.restore(out)
    assert config == configs.tiny("high_noise_partial")
    with np.load(TEST_DATA / "tiny_state_dict.npz") as expected:
        np.testing.assert_array_equal(params["temp_net"]["fc9"]["kernel"], expected["temp_net.nn.9.weight"].T)
    # A second conversion into the same directory is refused, leaving the first intact.
    assert convert.main([str(TEST_DATA / "tiny_state_dict.pth"), str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    checkpoint.restore(out)


def test_convert_command_reports_bad_files_in_one_line(tmp_path, capsys):
    bogus = tmp_path / "bogus.pth"
    bogus.write_bytes(b"not a checkpoint")
    assert convert.main([str(bogus), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "bogus.pth" in err and "\n" not in err
    assert not (tmp_path / "out").exists()
