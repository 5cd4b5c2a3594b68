import logging
import re

import h5py
import numpy as np
import pytest
from conftest import MODELNET_DIR

from dit_jax.data import shapes


def test_modelnet40_prepares_through_tfds_with_points_labels_and_ids(modelnet_test, modelnet_train):
    assert modelnet_train.points.shape == (9843, 1000, 3) and modelnet_test.points.shape == (2468, 1000, 3)
    assert modelnet_test.points.dtype == np.float32
    assert set(np.unique(modelnet_train.labels)) == set(range(40))
    assert modelnet_test.shape_names[0] == "airplane" and len(modelnet_test.shape_names) == 40
    # Ids name the source mesh, and its category agrees with the label.
    first = modelnet_test.ids[0]
    assert first.split("/")[0] == modelnet_test.shape_names[modelnet_test.labels[0]]
    # The first 1000 of the file's points, unchanged.
    with h5py.File(MODELNET_DIR / "ply_data_test0.h5") as f:
        np.testing.assert_array_equal(modelnet_test.points[0], f["data"][0, :1000])


def test_embedded_dataset_loads_offline(tmp_path):
    train = shapes.load_shapes(None, "train", n_points=1024, data_dir=str(tmp_path))
    test = shapes.load_shapes("embedded", "test", n_points=1024, data_dir=str(tmp_path))
    assert len(train.labels) + len(test.labels) == 820 and 100 < len(test.labels) < 250
    assert not set(train.ids) & set(test.ids)
    for split in (train, test):
        assert np.linalg.norm(split.points, axis=-1).max() <= 1.0
        np.testing.assert_allclose(split.points.mean(axis=1), 0.0, atol=1e-3)
        assert split.labels.min() >= -1 and split.labels.max() <= 39
    assert (train.labels >= 0).sum() > 200, "most furniture categories map to ModelNet40's"
    attribution = (shapes.EMBEDDED_FILE.parent / "ATTRIBUTION.md").read_text()
    assert all(f"| {i} |" in attribution for i in test.ids)


def _write_h5_dir(path, points, labels, names=True, key="data"):
    path.mkdir()
    for split in ("train", "test"):
        with h5py.File(path / f"ply_data_{split}0.h5", "w") as f:
            f[key] = points
            f["label"] = labels
    if names:
        (path / "shape_names.txt").write_text("\n".join(f"c{i}" for i in range(40)))
    return path


@pytest.mark.parametrize(
    "problem,pattern",
    [
        ("no_dir", r"no such directory"),
        ("no_files", r"no ply_data_train\*\.h5 files"),
        ("missing_key", r"ply_data_train0\.h5: missing key data"),
        ("few_points", r"holds 64 points per shape, fewer than the 1000 asked"),
        ("not_finite", r"ply_data_train0\.h5: shape 1 has non-finite coordinates"),
        ("no_names", r"no shape_names\.txt"),
        ("not_h5", r"ply_data_train0\.h5: not a readable HDF5 file"),
    ],
)
def test_bad_sources_give_one_line_errors(tmp_path, problem, pattern):
    points = np.random.default_rng(0).normal(size=(3, 1024, 3)).astype(np.float32)
    labels = np.zeros((3, 1), np.uint8)
    source = tmp_path / "modelnet"
    if problem == "no_files":
        source.mkdir()
    elif problem == "missing_key":
        _write_h5_dir(source, points, labels, key="points")
    elif problem == "few_points":
        _write_h5_dir(source, points[:, :64], labels)
    elif problem == "not_finite":
        points[1, 5, 2] = np.nan
        _write_h5_dir(source, points, labels)
    elif problem == "no_names":
        _write_h5_dir(source, points, labels, names=False)
    elif problem == "not_h5":
        _write_h5_dir(source, points, labels)
        (source / "ply_data_train0.h5").write_bytes(b"garbage")
    with pytest.raises(shapes.DataError, match=pattern) as err:
        shapes.load_shapes(source, "train", n_points=1000, data_dir=str(tmp_path / "prepared"))
    assert "\n" not in str(err.value)
    assert re.search(str(source.name), str(err.value))


def test_changed_source_is_prepared_again(tmp_path):
    points = np.random.default_rng(0).normal(size=(3, 16, 3)).astype(np.float32)
    source = _write_h5_dir(tmp_path / "src", points, np.zeros((3, 1), np.uint8))
    first = shapes.load_shapes(source, "test", n_points=16, data_dir=str(tmp_path / "p"))
    with h5py.File(source / "ply_data_test0.h5", "a") as f:
        f["data"][0] = points[0] + 1.0
    import os

    os.utime(source / "ply_data_test0.h5", (1, 1))  # make the change visible even within one second
    second = shapes.load_shapes(source, "test", n_points=16, data_dir=str(tmp_path / "p"))
    np.testing.assert_allclose(second.points[0], first.points[0] + 1.0)


_PREPARE = """
import sys, time
import numpy as np
start = float(sys.argv[2])
from dit_jax.data import shapes
while time.time() < start:  # both processes begin preparing at the same moment
    time.sleep(0.001)
data = shapes.load_shapes(None, "train", n_points=512, data_dir=sys.argv[1])
np.save(sys.argv[3], data.points[:4])
"""


def test_processes_preparing_the_same_data_at_once_all_get_it(tmp_path):
    """Two trainings started together on a fresh machine (or the processes of one multi-process run) used to
    race in TFDS's preparation, and one died with ``FileExistsError: Cannot rename .../incomplete...``.
    Now one prepares while the others wait, then they read what it wrote."""
    import subprocess
    import sys
    import time

    start = time.time() + 10.0  # after both interpreters have imported TFDS
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _PREPARE, str(tmp_path / "prepared"), str(start), str(tmp_path / f"out{i}.npy")],
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(3)
    ]
    errors = [p.communicate(timeout=600)[1] for p in procs]
    for p, err in zip(procs, errors):
        assert p.returncode == 0, err[-2000:]
    first = np.load(tmp_path / "out0.npy")
    for i in (1, 2):
        np.testing.assert_array_equal(np.load(tmp_path / f"out{i}.npy"), first)


def test_progress_false_prepares_without_tfds_bars_and_leaves_them_on(tmp_path, capfd, caplog):
    """`--no-progress` logs stay free of TFDS's bars while data is prepared, and of its warnings about our
    custom configs and the not yet prepared folder; later preparations show the bars."""
    points = np.random.default_rng(1).normal(size=(3, 32, 3)).astype(np.float32)
    source = _write_h5_dir(tmp_path / "modelnet", points, np.zeros((3, 1), np.uint8))
    quiet = shapes.load_shapes(source, "test", n_points=16, data_dir=str(tmp_path / "p"), progress=False)
    assert quiet.points.shape == (3, 16, 3)
    assert "%|" not in capfd.readouterr().err
    assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    shapes.load_shapes(source, "test", n_points=8, data_dir=str(tmp_path / "p"))  # another point count: prepared anew
    assert "%|" in capfd.readouterr().err
