"""Training the learned descriptor: its loss, its batches, its recipe, and `python train.py --config
configs/features.py` at tiny size on the shared rooms."""

import json
import os

import jax.numpy as jnp
import numpy as np
import pytest

from dit_jax.features import network
from dit_jax.training import descriptor, descriptor_data


def _unit(rows):
    return rows / np.linalg.norm(rows, axis=-1, keepdims=True)


def test_info_nce_is_low_and_accurate_where_each_row_lies_on_its_match():
    rng = np.random.default_rng(0)
    source = _unit(rng.normal(size=(2, 8, 16)))
    target = np.concatenate([source, _unit(rng.normal(size=(2, 4, 16)))], axis=1)
    near = np.zeros((2, 8, 12), bool)
    loss, accuracy = descriptor.info_nce(jnp.asarray(source), jnp.asarray(target), jnp.asarray(near), 0.1)
    shuffled = np.concatenate([source[:, ::-1], target[:, 8:]], axis=1)
    worse, wrong = descriptor.info_nce(jnp.asarray(source), jnp.asarray(shuffled), jnp.asarray(near), 0.1)
    assert float(accuracy) == 1.0 and float(loss) < 0.5
    assert float(worse) > float(loss) + 2 and float(wrong) < 0.5


def test_info_nce_does_not_count_rows_near_the_true_place():
    source = _unit(np.eye(4)[None, :2])  # two rows
    target = np.concatenate([source, source[:, :1]], axis=1)  # a third row equal to the first's match
    near = np.zeros((1, 2, 3), bool)
    counted, _ = descriptor.info_nce(jnp.asarray(source), jnp.asarray(target), jnp.asarray(near), 0.1)
    near[0, 0, 2] = True
    masked, _ = descriptor.info_nce(jnp.asarray(source), jnp.asarray(target), jnp.asarray(near), 0.1)
    assert float(masked) < float(counted)


def _scene(rng, voxel=0.05):
    points = rng.random((200, 3)).astype(np.float32)
    fragment = descriptor_data.Fragment(points, rng.random((200, 132), np.float32), rng.random((200, 33), np.float32))
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = descriptor_data.Fragment(points @ turn.T.astype(np.float32) + 1, fragment.histograms, fragment.fpfh)
    matched = descriptor_data.matching_keypoints(fragment, moved, turn, np.ones(3), 0.75 * voxel)
    pair = descriptor_data.KeypointPair("3DMatch", 0, 1, turn, np.ones(3), matched)
    return descriptor_data.Scene("toy", voxel, (fragment, moved), (pair, pair))


def test_matching_keypoints_and_batches_pair_each_keypoint_with_itself():
    rng = np.random.default_rng(1)
    scene = _scene(rng)
    assert np.array_equal(scene.pairs[0].matched[:, 0], scene.pairs[0].matched[:, 1])
    assert len(scene.pairs[0].matched) == 200
    batch = descriptor_data.draw_batch([scene], rng, pairs=2, anchors=16, negatives=8, near_voxels=2.0)
    assert batch.source.shape == (2, 16, 132) and batch.target.shape == (2, 24, 132) and batch.near.shape == (2, 16, 24)
    np.testing.assert_array_equal(batch.source, batch.target[:, :16])  # the same keypoint's histograms
    assert not batch.near[:, np.arange(16), np.arange(16)].any()
    with pytest.raises(ValueError, match="pairs have 500 matching keypoints"):
        descriptor_data.draw_batch([scene], rng, pairs=2, anchors=500, negatives=8, near_voxels=2.0)


def test_the_recipe_round_trips_through_json_and_refuses_unknown_fields():
    config = descriptor.DescriptorTrainConfig(holdout="hotel3", descriptor=network.DescriptorConfig(width=8))
    assert descriptor.DescriptorTrainConfig.from_json(json.loads(json.dumps(config.to_json()))) == config
    with pytest.raises(ValueError, match="unknown DescriptorTrainConfig fields: colour"):
        descriptor.DescriptorTrainConfig.from_json({"colour": 1})


TINY = [
    "--config", "configs/features.py", "--config.max_fragments=5", "--config.steps=6", "--config.pairs=2",
    "--config.anchors=16", "--config.negatives=16", "--config.eval_every=3", "--config.log_every=2",
    "--config.ckpt_every=3", "--config.descriptor.width=8", "--config.holdout=hotel3", "--no-progress",
]  # fmt: skip


def test_train_py_trains_the_descriptor_at_tiny_size_and_resumes(rooms_dir, tmp_path, capsys, monkeypatch):
    import train

    monkeypatch.chdir(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    workdir = tmp_path / "features"
    argv = [*TINY, f"--config.data_dir={rooms_dir}", "--workdir", str(workdir)]
    assert train.main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["validated_on"] == "hotel3"
    for name in ("fpfh", "histograms", "learned"):
        assert 0 <= result[name]["3DMatch"]["inlier_ratio"] <= 1
    weights = network.load(workdir / "descriptor")
    assert weights.config.width == 8 and weights.extra["scenes"] == ["home_md", "mit_lab"]
    assert (workdir / "curves.png").stat().st_size > 1000
    lines = (workdir / "metrics.jsonl").read_text().splitlines()
    assert train.main(argv) == 2  # a workdir with checkpoints is not overwritten
    assert "pass --resume" in capsys.readouterr().err
    assert train.main([*argv, "--resume"]) == 0  # at its end: validated again, nothing cut from the log
    assert (workdir / "metrics.jsonl").read_text().splitlines()[: len(lines)] == lines
    capsys.readouterr()

    import ship_weights  # the release tool writes it where the package's weights live, naming no machine's folder

    out = tmp_path / "shipped"
    ship_weights.main(
        [str(workdir), "--descriptor", "--command", "python train.py --config configs/features.py", "--out", str(out)]
    )
    shipped = network.load(out)
    assert shipped.extra["command"] == "python train.py --config configs/features.py"
    for marker in out.rglob("commit_success.txt"):
        assert str(tmp_path) not in marker.read_text()
