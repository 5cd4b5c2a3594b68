"""Reads PyTorch ``torch.save`` files (the zip format of PyTorch >= 1.6) into numpy, without PyTorch.

A saved state dict is a zip archive holding ``<archive>/data.pkl``, a pickle whose tensors refer to raw
storages stored beside it as ``<archive>/data/<key>``. Only what state dicts need is understood: tensors
rebuilt by ``torch._utils._rebuild_tensor_v2`` (or ``_rebuild_parameter``) over typed storages, in ordered or
plain dicts. Nothing else in the pickle is executed: any other global is refused, so a hostile file cannot run
code here.
"""

from __future__ import annotations

import collections
import pickle
import zipfile
from typing import Any

import numpy as np

_STORAGE_DTYPES = {
    "FloatStorage": np.float32,
    "DoubleStorage": np.float64,
    "HalfStorage": np.float16,
    "LongStorage": np.int64,
    "IntStorage": np.int32,
    "ShortStorage": np.int16,
    "CharStorage": np.int8,
    "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


class UnsupportedFile(ValueError):
    """The file is not a zip-format PyTorch save of tensors in dicts."""


class _Storage:
    def __init__(self, dtype):
        self.dtype = dtype


def _rebuild_tensor(storage: np.ndarray, offset: int, size, stride, *unused) -> np.ndarray:
    if len(size) == 0:
        return storage[offset].copy()
    itemsize = storage.dtype.itemsize
    view = np.lib.stride_tricks.as_strided(
        storage[offset:], shape=tuple(size), strides=tuple(s * itemsize for s in stride)
    )
    return np.array(view)  # a contiguous copy, independent of the archive


def _rebuild_parameter(data, requires_grad, backward_hooks, *unused):
    return data


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, archive: zipfile.ZipFile, prefix: str):
        super().__init__(file)
        self._archive = archive
        self._prefix = prefix

    def find_class(self, module: str, name: str):
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if module == "torch._utils" and name == "_rebuild_tensor_v2":
            return _rebuild_tensor
        if module == "torch._utils" and name == "_rebuild_parameter":
            return _rebuild_parameter
        if module == "torch" and name in _STORAGE_DTYPES:
            return _Storage(_STORAGE_DTYPES[name])
        raise UnsupportedFile(f"refusing pickled global {module}.{name} (only tensors in dicts are read)")

    def persistent_load(self, pid):
        kind, storage_type, key, _location, numel = pid[:5]
        if kind != "storage":
            raise UnsupportedFile(f"unknown persistent id {kind!r}")
        if isinstance(storage_type, _Storage):
            dtype = storage_type.dtype
        else:  # newer PyTorch pickles torch.<dtype> objects; their names are refused by find_class above
            raise UnsupportedFile(f"unknown storage type {storage_type!r}")
        raw = self._archive.read(f"{self._prefix}/data/{key}")
        return np.frombuffer(raw, dtype=dtype, count=numel)


def load(path: str) -> Any:
    """Loads a zip-format ``torch.save`` file; tensors become numpy arrays."""
    if not zipfile.is_zipfile(path):
        raise UnsupportedFile(f"{path}: not a zip-format PyTorch file (saved before PyTorch 1.6?)")
    with zipfile.ZipFile(path) as archive:
        pickles = [n for n in archive.namelist() if n.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise UnsupportedFile(f"{path}: expected one data.pkl in the archive, found {len(pickles)}")
        prefix = pickles[0][: -len("/data.pkl")]
        with archive.open(pickles[0]) as f:
            return _Unpickler(f, archive, prefix).load()
