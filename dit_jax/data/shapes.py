"""Shape collections through TFDS: ModelNet40 in the standard h5 layout, and the embedded furniture set.

A TFDS builder (:class:`PointCloudShapes`) prepares array_record files once per source and point count and
serves them through ``as_data_source()`` (random access, no TensorFlow needed). :func:`load_shapes` returns one
split of it as arrays in memory::

    shapes = load_shapes("/data/modelnet40_ply_hdf5_2048", "test", n_points=1000)   # ModelNet40
    shapes = load_shapes(None, "train")                                              # the embedded set

Sources:

* a directory in the layout of ``modelnet40_ply_hdf5_2048``: ``ply_data_{train,test}<i>.h5`` with ``data``
  (S, P, 3) and ``label`` (S, 1), ``shape_names.txt``, optionally ``ply_data_<split>_<i>_id2file.json``;
* ``None`` or ``"embedded"``: 820 furniture models from Debian's ``sweethome3d-furniture`` package shipped with
  dit-jax (``dit_jax/data/embedded``), 1024 points each, a ModelNet40 label where the name gives one (else -1),
  a fixed 80/20 train/test split by id.

Each shape keeps its first ``n_points`` points, as the authors' loader does.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import json
import logging
import os
import pathlib
import re
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import tensorflow_datasets as tfds

EMBEDDED = "embedded"
EMBEDDED_FILE = pathlib.Path(__file__).with_name("embedded") / "sh3d_furniture_1024.npz"
EMBEDDED_QUANT = 32767
SPLITS = ("train", "test")
DEFAULT_DATA_DIR = os.environ.get("DIT_JAX_DATA_DIR", os.path.join(os.path.expanduser("~"), ".cache", "dit_jax"))


class DataError(ValueError):
    """A source directory or file cannot be read as asked; the message names it and the problem."""


class Shapes(NamedTuple):
    """One split of a shape collection, in memory. S shapes of P points."""

    points: np.ndarray  # (S, P, 3) float32
    labels: np.ndarray  # (S,) int64, ModelNet40 category 0..39, or -1 where unknown
    ids: np.ndarray  # (S,) str, where each shape came from
    shape_names: tuple[str, ...]  # category names by label


# ---------------------------------------------------------------------------------------------------- sources


def _h5_files(source: pathlib.Path, split: str) -> list[pathlib.Path]:
    files = [pathlib.Path(p) for p in glob.glob(str(source / f"ply_data_{split}*.h5"))]
    number = lambda p: int(re.findall(r"(\d+)\.h5$", p.name)[0]) if re.search(r"\d+\.h5$", p.name) else 0
    return sorted(files, key=number)


def check_h5_source(source: str | os.PathLike, n_points: int) -> pathlib.Path:
    """Validates a ModelNet40 h5 directory cheaply (files, keys, point count) and returns its path."""
    path = pathlib.Path(source).expanduser().resolve()
    if not path.is_dir():
        raise DataError(f"{path}: no such directory (expected ModelNet40 in the modelnet40_ply_hdf5_2048 layout)")
    import h5py

    for split in SPLITS:
        files = _h5_files(path, split)
        if not files:
            raise DataError(f"{path}: no ply_data_{split}*.h5 files (expected the modelnet40_ply_hdf5_2048 layout)")
        for file in files:
            try:
                with h5py.File(file, "r") as f:
                    missing = [k for k in ("data", "label") if k not in f]
                    if missing:
                        raise DataError(f"{file}: missing key {', '.join(missing)} (has {', '.join(f.keys())})")
                    shape = f["data"].shape
            except OSError as err:
                raise DataError(f"{file}: not a readable HDF5 file ({err})") from None
            if len(shape) != 3 or shape[2] != 3:
                raise DataError(f"{file}: 'data' has shape {shape}, expected (shapes, points, 3)")
            if shape[1] < n_points:
                raise DataError(f"{file}: holds {shape[1]} points per shape, fewer than the {n_points} asked")
    if not (path / "shape_names.txt").exists():
        raise DataError(f"{path}: no shape_names.txt (the 40 category names in label order)")
    return path


def _read_h5_split(path: pathlib.Path, split: str, n_points: int) -> Iterator[tuple[str, np.ndarray, int]]:
    import h5py

    for file in _h5_files(path, split):
        with h5py.File(file, "r") as f:
            data = np.asarray(f["data"][:, :n_points, :], dtype=np.float32)
            labels = np.asarray(f["label"]).reshape(-1).astype(np.int64)
        if len(labels) != len(data):
            raise DataError(f"{file}: {len(data)} shapes but {len(labels)} labels")
        bad = ~np.isfinite(data).all(axis=(1, 2))
        if bad.any():
            raise DataError(f"{file}: shape {int(np.argmax(bad))} has non-finite coordinates")
        if labels.min() < 0 or labels.max() > 39:
            raise DataError(f"{file}: labels outside 0..39")
        id_file = file.with_name(file.stem.replace(f"ply_data_{split}", f"ply_data_{split}_") + "_id2file.json")
        ids = json.loads(id_file.read_text()) if id_file.exists() else None
        if ids is None or len(ids) != len(data):
            ids = [f"{file.name}:{row}" for row in range(len(data))]
        yield from zip(ids, data, labels.tolist())


def _embedded_split(ids: np.ndarray) -> np.ndarray:
    """True for test shapes: a fixed 20 % chosen by a hash of the id (same on every machine)."""
    return np.array([hashlib.sha256(i.encode()).digest()[0] % 5 == 0 for i in ids.tolist()])


def _read_embedded(split: str, n_points: int) -> Iterator[tuple[str, np.ndarray, int]]:
    with np.load(EMBEDDED_FILE) as z:
        points = z["points"].astype(np.float32) / EMBEDDED_QUANT
        labels, ids = z["label"].astype(np.int64), z["id"]
    if points.shape[1] < n_points:
        raise DataError(f"{EMBEDDED_FILE}: holds {points.shape[1]} points per shape, fewer than the {n_points} asked")
    test = _embedded_split(ids)
    keep = test if split == "test" else ~test
    for i in np.flatnonzero(keep):
        yield str(ids[i]), points[i, :n_points], int(labels[i])


def _shape_names(source: str) -> tuple[str, ...]:
    if source == EMBEDDED:
        with np.load(EMBEDDED_FILE) as z:
            return tuple(str(s) for s in z["shape_names"])
    return tuple(pathlib.Path(source, "shape_names.txt").read_text().split())


def _fingerprint(source: str) -> str:
    """Changes when the source's files change, so a prepared copy is never stale."""
    if source == EMBEDDED:
        files = [EMBEDDED_FILE]
    else:
        files = sorted(pathlib.Path(source).glob("*"))
    h = hashlib.sha256(source.encode())
    for f in files:
        st = f.stat()
        h.update(f"{f.name}:{st.st_size}:{int(st.st_mtime)}".encode())
    return h.hexdigest()[:10]


# ---------------------------------------------------------------------------------------------------- TFDS


@dataclasses.dataclass
class ShapesConfig(tfds.core.BuilderConfig):
    """Which source and how many points per shape; the name carries the source's fingerprint."""

    source: str = EMBEDDED
    n_points: int = 1024


class PointCloudShapes(tfds.core.GeneratorBasedBuilder):
    """Point-cloud shapes with their label and id, from a ModelNet40 h5 directory or the embedded set."""

    VERSION = tfds.core.Version("1.0.0")
    BUILDER_CONFIG_CLASS = ShapesConfig

    def _info(self):
        c = self.builder_config
        return tfds.core.DatasetInfo(
            builder=self,
            disable_shuffling=True,  # keep the source's order, so row i is the file's shape i
            description=f"Point clouds of {c.n_points} points from {c.source}",
            features=tfds.features.FeaturesDict(
                {
                    "points": tfds.features.Tensor(shape=(c.n_points, 3), dtype=np.float32),
                    "label": tfds.features.Scalar(dtype=np.int64),
                    "id": tfds.features.Text(),
                }
            ),
        )

    def _split_generators(self, dl_manager):
        return {split: self._generate_examples(split) for split in SPLITS}

    def _generate_examples(self, split):
        c = self.builder_config
        if c.source == EMBEDDED:
            rows = _read_embedded(split, c.n_points)
        else:
            rows = _read_h5_split(pathlib.Path(c.source), split, c.n_points)
        for key, (shape_id, points, label) in enumerate(rows):
            yield key, {"points": points, "label": label, "id": shape_id}


def source_points(source: str | os.PathLike | None = None) -> int:
    """How many points each shape of ``source`` (a ModelNet40 h5 directory, or None for the embedded set)
    holds: what settings that sample the two clouds from disjoint points draw from."""
    if source is None or str(source) == EMBEDDED:
        with np.load(EMBEDDED_FILE) as z:
            return int(z["points"].shape[1])
    import h5py

    path = check_h5_source(source, 1)
    with h5py.File(_h5_files(path, "train")[0], "r") as f:
        return int(f["data"].shape[1])


def builder(source: str | os.PathLike | None = None, n_points: int = 1000, data_dir: str | None = None):
    """The TFDS builder of ``source`` (a ModelNet40 h5 directory, or None for the embedded set).

    Nothing is prepared yet; call ``download_and_prepare()`` (or use :func:`load_shapes`).
    """
    if n_points < 1:
        raise DataError(f"n_points must be positive, got {n_points}")
    if source is None or str(source) == EMBEDDED:
        source = EMBEDDED
        if not EMBEDDED_FILE.exists():
            raise DataError(f"{EMBEDDED_FILE}: the embedded dataset is missing from this installation")
        with np.load(EMBEDDED_FILE) as z:
            if z["points"].shape[1] < n_points:
                raise DataError(
                    f"{EMBEDDED_FILE}: holds {z['points'].shape[1]} points per shape, fewer than the {n_points} asked"
                )
    else:
        source = str(check_h5_source(source, n_points))
    name = f"{'embedded' if source == EMBEDDED else 'h5'}_p{n_points}_{_fingerprint(source)}"
    config = ShapesConfig(name=name, source=source, n_points=n_points)
    with _tfds_warnings_hidden():  # TFDS warns about every custom config, which all of ours are
        return PointCloudShapes(
            config=config, data_dir=os.path.join(data_dir or DEFAULT_DATA_DIR, "tfds"), file_format="array_record"
        )


@contextlib.contextmanager
def _tfds_warnings_hidden():
    """TFDS's warnings (through absl) hidden, its errors kept."""
    absl_logger = logging.getLogger("absl")
    level = absl_logger.level
    absl_logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        absl_logger.setLevel(level)


def prepare(
    source: str | os.PathLike | None = None, n_points: int = 1000, data_dir: str | None = None, progress: bool = True
):
    """:func:`builder`'s builder, prepared: once per ``data_dir``, however many processes ask at once;
    ``progress=False`` hides TFDS's progress bars while it prepares (for logs written to files).

    TFDS writes into a temporary folder and renames it, so two processes preparing the same data at once
    (two trainings started together, every process of a multi-process run) both write, and the second
    rename fails. Here the first process to take a lock file next to the data prepares; the others wait for
    the lock, then find the data prepared and read it.
    """
    b = builder(source, n_points, data_dir)
    with _tfds_warnings_hidden():  # before the first preparation TFDS warns that the folder holds no data yet
        prepared = b.is_prepared()
    if prepared:
        return b
    os.makedirs(b.data_dir_root, exist_ok=True)
    with open(os.path.join(b.data_dir_root, f".{b.builder_config.name}.lock"), "a") as lock:
        _lock(lock)
        b = builder(source, n_points, data_dir)  # afresh: it sees what another process prepared meanwhile
        if progress:
            b.download_and_prepare()
        else:
            tfds.display_progress_bar(False)
            try:
                b.download_and_prepare()
            finally:
                tfds.display_progress_bar(True)
    return b  # closing the file releases the lock


def _lock(file) -> None:
    """Blocks until this process holds an exclusive lock on ``file`` (released when it is closed)."""
    try:
        import fcntl
    except ImportError:  # Windows: no flock; concurrent preparation stays unguarded there
        return
    fcntl.flock(file.fileno(), fcntl.LOCK_EX)


def load_shapes(
    source: str | os.PathLike | None = None,
    split: str = "train",
    n_points: int = 1000,
    data_dir: str | None = None,
    progress: bool = True,
) -> Shapes:
    """One split of a shape collection as arrays, preparing it through TFDS the first time.

    Args:
      source: a ModelNet40 directory in the h5 layout, or None / "embedded" for the shipped furniture set.
      split: "train" or "test" (the official split for ModelNet40).
      n_points: points kept per shape (the first ones, as the authors do).
      data_dir: where prepared data lives (default ``$DIT_JAX_DATA_DIR`` or ``~/.cache/dit_jax``).
      progress: show TFDS's progress bars if it prepares the data now.

    Raises:
      DataError: one line naming the file or directory and the problem.
    """
    if split not in SPLITS:
        raise DataError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    b = prepare(source, n_points, data_dir, progress)
    data_source = b.as_data_source()[split]
    n = len(data_source)
    points = np.empty((n, n_points, 3), np.float32)
    labels = np.empty(n, np.int64)
    ids = []
    chunk = 1024
    for start in range(0, n, chunk):
        items = data_source.__getitems__(list(range(start, min(n, start + chunk))))
        for offset, item in enumerate(items):
            points[start + offset] = item["points"]
            labels[start + offset] = item["label"]
            ids.append(item["id"].decode() if isinstance(item["id"], bytes) else str(item["id"]))
    return Shapes(points, labels, np.asarray(ids), _shape_names(b.builder_config.source))
