import numpy as np

from dit_jax.data import pairs, prefetch, shapes


def _dataset(tmp_path, train):
    s = shapes.load_shapes(None, "test", n_points=1024, data_dir=str(tmp_path))
    return pairs.PairDataset(s, pairs.PairConfig(setting="high_noise_partial", train=train, n_points=1024))


def test_an_epoch_visits_every_pair_once(tmp_path):
    ds = _dataset(tmp_path, train=False)
    seen = np.concatenate([b["index"] for b in prefetch.batches(ds, 16)])
    np.testing.assert_array_equal(seen, np.arange(len(ds)))


def test_training_batches_shuffle_drop_remainder_and_resume(tmp_path):
    ds = _dataset(tmp_path, train=True)
    full = list(prefetch.batches(ds, 8, epoch=2))
    assert len(full) == len(ds) // 8 and all(b["src"].shape[0] == 8 for b in full)
    order = np.concatenate([b["index"] for b in full])
    assert not np.array_equal(order, np.sort(order))
    resumed = list(prefetch.batches(ds, 8, epoch=2, start_batch=5))
    for a, b in zip(full[5:], resumed):
        np.testing.assert_array_equal(a["tgt"], b["tgt"])
    other_epoch = np.concatenate([b["index"] for b in prefetch.batches(ds, 8, epoch=3)])
    assert not np.array_equal(order, other_epoch)


def test_prefetch_changes_nothing(tmp_path):
    ds = _dataset(tmp_path, train=True)
    with_prefetch = list(prefetch.batches(ds, 8, prefetch=3))
    without = list(prefetch.batches(ds, 8, prefetch=0))
    for a, b in zip(with_prefetch, without, strict=True):
        np.testing.assert_array_equal(a["src"], b["src"])
