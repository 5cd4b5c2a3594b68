"""Packed shapes (tools/packed.py): what a lent GPU trains on must be the shapes, split and validation
pairs a run here would use."""

import subprocess
import sys

import numpy as np
import packed
import pytest
from conftest import ROOT
from test_data_shapes import _write_h5_dir

from dit_jax import training
from dit_jax.data import shapes


def _source(tmp_path):
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.9, 0.9, size=(60, 32, 3)).astype(np.float32)
    labels = rng.integers(0, 40, size=(60, 1)).astype(np.uint8)
    return _write_h5_dir(tmp_path / "modelnet", points, labels), points, labels.ravel()


def test_packed_split_keeps_the_shapes_rows_and_validation_split(tmp_path):
    source, points, labels = _source(tmp_path)
    summary = packed.pack(str(source), str(tmp_path / "p.npz"), labels=range(20))
    kept = labels < 20
    assert summary["shapes"] == 60 and summary["kept"] == kept.sum()
    got = packed.load(str(tmp_path / "p.npz"), n_points=24)
    assert got.points.shape == (60, 24, 3) and got.points.dtype == np.float32
    np.testing.assert_array_equal(got.labels, labels)
    np.testing.assert_allclose(got.points[kept], points[kept, :24], atol=0.5 / packed.QUANT + 1e-7)
    assert not got.points[~kept].any(), "shapes of other categories do not travel"
    # the same validation shapes as the source read directly
    original = shapes.Shapes(
        points,
        labels.astype(np.int64),
        np.array([r[0] for r in shapes._read_h5_split(source, "train", 32)]),
        got.shape_names,
    )
    _, val_original = training.split_validation(original, 0.1)
    _, val_packed = training.split_validation(got, 0.1)
    keep = val_original.labels < 20
    np.testing.assert_array_equal(val_packed.ids[keep], val_original.ids[keep])
    with pytest.raises(ValueError, match="fewer than the 64 asked"):
        packed.load(str(tmp_path / "p.npz"), n_points=64)


def test_points_beyond_the_unit_cube_are_refused(tmp_path):
    points = np.full((2, 8, 3), 1.5, np.float32)
    source = _write_h5_dir(tmp_path / "big", points, np.zeros((2, 1), np.uint8))
    with pytest.raises(ValueError, match="beyond the unit cube"):
        packed.pack(str(source), str(tmp_path / "p.npz"))
    assert not (tmp_path / "p.npz").exists()


def test_shapes_module_imports_without_tfds(tmp_path):
    """The lent GPU machine has no tensorflow_datasets; the data modules must still import there."""
    (tmp_path / "tensorflow_datasets.py").write_text("raise ImportError('not installed here')\n")
    code = (
        "import packed; assert packed.allow_without_tfds(); "
        "from dit_jax.data import pairs, shapes; from dit_jax import training; print('ok')"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={"PYTHONPATH": f"{tmp_path}:{ROOT}:{ROOT / 'tools'}", "PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu"},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "ok"
