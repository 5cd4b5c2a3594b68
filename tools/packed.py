"""Shapes packed into one file, for a machine that has neither the data directory nor TFDS (a lent GPU): a
development tool beside tools/device_stage.py, not part of the package.

:func:`pack` writes one split of a ModelNet40 h5 directory, keeping only the shapes a run can use (with
``unseen``, categories 0-19) and the row count of the whole split, so that
:func:`dit_jax.training.split_validation` draws the same validation shapes there as here. Points travel as
int16 (resolution 1/32767 of the unit sphere, 3e-5), half the size of float32::

    pack("/data/modelnet40_ply_hdf5_1024", "runs/device_data/mn40_train.npz", labels=range(20))
    shapes = load("runs/device_data/mn40_train.npz")     # Shapes, unused rows zero, their labels kept

:func:`allow_without_tfds` lets :mod:`dit_jax.data.shapes` import where ``tensorflow_datasets`` is missing
(its TFDS builder then goes unused); call it before anything imports that module.
"""

from __future__ import annotations

import pathlib
import sys
import types
from collections.abc import Iterable

import numpy as np

QUANT = 32767


def allow_without_tfds() -> bool:
    """Installs a stand-in ``tensorflow_datasets`` module where the real one is missing; True if it did."""
    try:
        import tensorflow_datasets  # noqa: F401

        return False
    except ImportError:
        stub = types.ModuleType("tensorflow_datasets")
        unused = type("Unused", (), {"__init__": lambda self, *a, **k: None})
        stub.core = types.SimpleNamespace(
            BuilderConfig=unused, GeneratorBasedBuilder=unused, Version=unused, DatasetInfo=unused
        )
        stub.features = types.SimpleNamespace(FeaturesDict=unused, Tensor=unused, Scalar=unused, Text=unused)
        sys.modules["tensorflow_datasets"] = stub
        return True


def pack(source: str, out: str, split: str = "train", labels: Iterable[int] | None = None) -> dict:
    """Writes ``split`` of the h5 directory ``source`` to ``out`` (.npz); returns a summary.

    Args:
      labels: categories whose shapes are kept (the others keep only their label); None keeps all.
    """
    from dit_jax.data import shapes as shapes_lib

    path = shapes_lib.check_h5_source(source, 1)
    rows = list(shapes_lib._read_h5_split(path, split, 10**9))
    all_labels = np.array([r[2] for r in rows], np.int64)
    keep = np.ones(len(rows), bool) if labels is None else np.isin(all_labels, list(labels))
    kept = np.flatnonzero(keep)
    points = np.stack([rows[i][1] for i in kept])
    if np.abs(points).max() > 1.0:
        raise ValueError(f"{source}: coordinates beyond the unit cube cannot be packed as int16")
    out_path = pathlib.Path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        out_path,
        points=np.round(points * QUANT).astype(np.int16),
        rows=kept,
        labels=all_labels,
        ids=np.array([rows[i][0] for i in kept]),
        shape_names=np.array(shapes_lib._shape_names(str(path))),
        source=np.array(str(source)),
        split=np.array(split),
    )
    return {"out": str(out_path), "shapes": len(rows), "kept": int(len(kept)), "bytes": out_path.stat().st_size}


def load(path: str, n_points: int | None = None):
    """The packed split as :class:`dit_jax.data.shapes.Shapes`, every row of the original split in its
    place; rows that were not kept hold zeros and keep their label (training never reads them)."""
    from dit_jax.data.shapes import Shapes

    with np.load(path) as z:
        stored = z["points"]
        n = stored.shape[1] if n_points is None else n_points
        if n > stored.shape[1]:
            raise ValueError(f"{path}: holds {stored.shape[1]} points per shape, fewer than the {n} asked")
        labels = z["labels"]
        points = np.zeros((len(labels), n, 3), np.float32)
        points[z["rows"]] = stored[:, :n].astype(np.float32) / QUANT
        ids = np.array([f"unpacked:{i}" for i in range(len(labels))], dtype=object)
        ids[z["rows"]] = z["ids"]
        return Shapes(points, labels, ids.astype(str), tuple(str(s) for s in z["shape_names"]))
