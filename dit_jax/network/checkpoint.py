"""Model checkpoints on orbax: the params and the :class:`DITConfig` they belong to, in one directory.

Layout (an orbax composite checkpoint)::

    DIR/params/   the params tree (orbax StandardSave)
    DIR/config/   {"format": 1, "dit_config": {...}} (JSON)

Saving is atomic (orbax writes to a temporary directory and renames it), so an interrupted save leaves no
half-written checkpoint behind. Restoring checks the stored tree against the stored config.

Restoring through orbax (importing it, opening its tensor store) takes several times as long as the arrays
take to read. While the compilation cache is on (:mod:`dit_jax.network.compile_cache`), :func:`restore` therefore
keeps a plain copy of the params there, keyed by a digest of the checkpoint's params files, and later
restores read that copy instead: the same arrays, bit for bit, and a checkpoint that changes gets a new key.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from typing import Any

import jax
import numpy as np

from dit_jax.network import compile_cache
from dit_jax.network.configs import DITConfig

FORMAT = 1


class CheckpointError(ValueError):
    """A checkpoint is missing, damaged or does not fit its config."""


def _ocp():
    import orbax.checkpoint as ocp  # slow to import; a restore from the cache's copy never needs it

    return ocp


def _handler():
    ocp = _ocp()
    return ocp.Checkpointer(ocp.CompositeCheckpointHandler())


def save(
    directory: str | os.PathLike, params: Any, config: DITConfig, *, overwrite: bool = False, extra: dict | None = None
) -> str:
    """Writes ``params`` and ``config`` to ``directory`` (which must not exist unless ``overwrite``).

    ``extra``: JSON-able facts about how the params were made (training data, point count, steps), read back
    by :func:`read_extra`. Returns the absolute path written.
    """
    path = os.path.abspath(os.fspath(directory))
    if os.path.exists(path) and not overwrite:
        raise CheckpointError(f"{path} already exists; choose a new directory")
    meta = {"format": FORMAT, "dit_config": config.to_dict(), "extra": extra or {}}
    ocp = _ocp()
    with _handler() as ckptr:
        ckptr.save(
            path,
            ocp.args.Composite(params=ocp.args.StandardSave(params), config=ocp.args.JsonSave(meta)),
            force=overwrite,
        )
    return path


def read_extra(directory: str | os.PathLike) -> dict:
    """The ``extra`` facts stored with a checkpoint (empty if none)."""
    return _read_meta(directory).get("extra", {})


def update_extra(directory: str | os.PathLike, changes: dict) -> None:
    """Adds ``changes`` to a checkpoint's ``extra`` record (:func:`read_extra`) in place. Only the record's
    JSON file is rewritten (atomically), so the params' files stay byte for byte: a shipped checkpoint
    takes a newly measured setting without a new copy of its weights."""
    meta = _read_meta(directory)
    meta["extra"] = {**meta.get("extra", {}), **changes}
    _write_meta(directory, meta)


def update_config(directory: str | os.PathLike, changes: dict) -> DITConfig:
    """Replaces fields of a checkpoint's stored :class:`DITConfig` in place, as :func:`update_extra` does
    the record: for inference settings chosen after training (``n_iters``, GMCCE options), which no param
    depends on. A change that would alter the params' tree or shapes is refused. Returns the new config."""
    meta = _read_meta(directory)
    old = DITConfig.from_dict(meta["dit_config"])
    try:
        new = old.replace(**changes)
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"{os.path.abspath(os.fspath(directory))}: cannot apply {changes}: {err}") from None
    if param_shapes(old) != param_shapes(new):
        raise CheckpointError(
            f"{os.path.abspath(os.fspath(directory))}: {changes} would change the params' "
            f"shapes; train or convert a new checkpoint instead"
        )
    meta["dit_config"] = new.to_dict()
    _write_meta(directory, meta)
    return new


def _write_meta(directory: str | os.PathLike, meta: dict) -> None:
    """Rewrites a checkpoint's record file atomically and checks that it reads back."""
    target = os.path.join(os.path.abspath(os.fspath(directory)), "config", "metadata")
    if not os.path.isfile(target):
        raise CheckpointError(f"{os.path.dirname(os.path.dirname(target))}: no record file to update")
    staging = target + ".new"
    with open(staging, "w") as f:
        json.dump(meta, f)
    os.replace(staging, target)
    if _read_meta(directory) != json.loads(json.dumps(meta)):
        raise CheckpointError(f"{target}: the updated record does not read back")


def read_config(directory: str | os.PathLike) -> DITConfig:
    """The :class:`DITConfig` stored in a checkpoint."""
    meta = _read_meta(directory)
    try:
        return DITConfig.from_dict(meta["dit_config"])
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"{os.path.abspath(os.fspath(directory))}: stored config is invalid: {err}") from None


def _read_meta(directory: str | os.PathLike) -> dict:
    path = os.path.abspath(os.fspath(directory))
    if not os.path.isdir(path):
        raise CheckpointError(f"{path}: no such checkpoint directory")
    try:  # orbax's JSON item is one plain file: read it without orbax
        with open(os.path.join(path, "config", "metadata")) as f:
            meta = json.load(f)
        if isinstance(meta, dict) and meta.get("format") == FORMAT and "dit_config" in meta:
            return meta
    except (OSError, ValueError):
        pass
    ocp = _ocp()
    try:
        with _handler() as ckptr:
            meta = ckptr.restore(path, ocp.args.Composite(config=ocp.args.JsonRestore())).config
    except Exception as err:  # orbax raises many types for damaged files
        raise CheckpointError(f"{path}: not a dit-jax checkpoint or damaged ({type(err).__name__}: {err})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or "dit_config" not in meta:
        raise CheckpointError(f"{path}: unknown checkpoint format (expected format {FORMAT})")
    return meta


def restore(directory: str | os.PathLike) -> tuple[Any, DITConfig]:
    """Restores ``(params, config)`` from a checkpoint written by :func:`save`.

    Raises:
      CheckpointError: with one line naming the directory and the problem.
    """
    config = read_config(directory)
    path = os.path.abspath(os.fspath(directory))
    copy = _params_copy_path(path)
    params = _cached_params(copy)
    if params is None:
        # As host arrays, as the copy gives them: placed on the device the same way, both compile to one
        # program (one key in XLA's cache) whichever way the weights were read.
        params = jax.tree.map(np.asarray, _restore_params(path))
        _keep_params(copy, params)
    stored = _shapes(params)
    expected = param_shapes(config)
    if stored != expected:
        wrong = sorted(set(stored.items()) ^ set(expected.items()))[0][0]
        raise CheckpointError(
            f"{path}: params do not restore for the stored config (first difference at "
            f"{wrong}: stored {stored.get(wrong)}, the config needs {expected.get(wrong)})"
        )
    return jax.device_put(params), config


def _restore_params(path: str) -> Any:
    """The params tree of the checkpoint at ``path``, through orbax."""
    ocp = _ocp()
    try:
        with _handler() as ckptr:
            return ckptr.restore(path, ocp.args.Composite(params=ocp.args.StandardRestore())).params
    except Exception as err:
        raise CheckpointError(
            f"{path}: params do not restore for the stored config "
            f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})"
        ) from None


def _params_copy_path(path: str) -> str | None:
    """Where the compilation cache keeps a plain copy of this checkpoint's params (None: the cache is off or
    the checkpoint has no params folder). The name is a digest of every file under ``path/params``."""
    if compile_cache.directory() is None or not os.path.isdir(os.path.join(path, "params")):
        return None
    digest = hashlib.sha256()
    for root, dirs, files in os.walk(os.path.join(path, "params")):
        dirs.sort()
        for name in sorted(files):
            file = os.path.join(root, name)
            digest.update(os.path.relpath(file, path).encode() + b"\0")
            try:
                with open(file, "rb") as f:
                    digest.update(f.read())
            except OSError:
                return None
    return os.path.join(compile_cache.directory(), "params", digest.hexdigest()[:32] + ".npz")


def _cached_params(copy: str | None) -> dict | None:
    """The params tree from the cache's copy at ``copy`` (:func:`_params_copy_path`), or None where there is
    none to read."""
    if copy is None or not os.path.isfile(copy):
        return None
    try:
        with np.load(copy, allow_pickle=False) as arrays:
            flat = {name: arrays[name] for name in arrays.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):  # damaged: orbax, and a fresh copy
        return None
    tree: dict = {}
    for name, value in flat.items():
        *parents, leaf = name.split("/")
        node = tree
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def _keep_params(copy: str | None, params: Any) -> None:
    """Writes the cache's plain copy of ``params`` (nested dicts of arrays, as orbax restores them) to ``copy``
    (None: none); a tree of any other kind, or a failed write, leaves no copy."""
    if copy is None:
        return
    flat = {}
    for keys, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        if not all(isinstance(k, jax.tree_util.DictKey) and "/" not in str(k.key) for k in keys):
            return
        flat["/".join(str(k.key) for k in keys)] = np.asarray(leaf)
    buffer = io.BytesIO()
    np.savez(buffer, **flat)
    compile_cache.write_atomically(copy, buffer.getvalue())


def param_shapes(config: DITConfig) -> dict[str, tuple[int, ...]]:
    """The shape of each parameter ``config`` makes, by its path ("a/b/kernel"). Tracing the model's init
    costs more than restoring its weights, so the answer is kept in the compilation cache where it is on."""

    def compute():
        from dit_jax.network import model

        return {
            name: list(shape)
            for name, shape in _shapes(jax.eval_shape(lambda: model.init(jax.random.key(0), config))).items()
        }

    return {name: tuple(shape) for name, shape in compile_cache.memo("param-shapes", config, compute).items()}


def _shapes(tree) -> dict[str, tuple[int, ...]]:
    flat = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {"/".join(str(getattr(k, "key", k)) for k in path): tuple(np.shape(leaf)) for path, leaf in flat}
