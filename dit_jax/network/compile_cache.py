"""JAX's persistent compilation cache for the command-line tools (``dit-register``, ``train.py``, ``evaluate.py``).

XLA compiles DIT's registration for each config and cloud size; on a CPU that takes longer than the
registration itself. With the cache on, a second process with the same shapes loads the compiled program
from disk instead (timings: docs/benchmarks.md).

The directory, in order: ``--compile-cache DIR``; the environment variable ``DIT_JAX_COMPILE_CACHE``;
``$XDG_CACHE_HOME/dit-jax/xla``, else ``~/.cache/dit-jax/xla``. ``--no-compile-cache`` (or the variable set
to ``off``) turns it off. A directory that cannot be created leaves the cache off with a note on stderr:
caching only saves time, so it never stops a run.

XLA's cache skips compiling, not tracing: the Python that builds a program (Flax's modules, each parameter's
shape check) still runs in every process. So :func:`call` also keeps the traced program itself, exported
with :mod:`jax.export`, under ``DIR/exported/``, and :func:`memo` keeps small results that depend only on the
code and a config (the shapes a config's parameters must have). Their keys include a digest of the package's
source, JAX's version and the settings that change tracing, so an edit to the code never reuses a stale one.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import os
import pathlib
import sys
import tempfile

#: Overrides the default directory; "off" turns the cache off.
ENV_VAR = "DIT_JAX_COMPILE_CACHE"

#: The directory in use (None: off), and whether this process has chosen (a tool's flags, or :func:`enable`).
_enabled: dict = {"directory": None, "chosen": False}
#: In this process: a key's program, deserialized once.
_programs: dict[str, object] = {}


def default_dir() -> str | None:
    """The directory used when no flag says otherwise; None where the environment turns the cache off."""
    chosen = os.environ.get(ENV_VAR)
    if chosen:
        return None if chosen.lower() == "off" else chosen
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "dit-jax", "xla")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--compile-cache DIR`` and ``--no-compile-cache``."""
    parser.add_argument(
        "--compile-cache",
        default=None,
        metavar="DIR",
        help=f"keep compiled XLA programs here, so the next run starts without compiling "
        f"(default: ${ENV_VAR}, else ~/.cache/dit-jax/xla)",
    )
    parser.add_argument("--no-compile-cache", action="store_true", help="compile afresh every run")


def enable(directory: str | None) -> str | None:
    """Points JAX's persistent compilation cache at ``directory`` (created if missing) and caches every
    program, however quick to compile. Call before the first compilation. Returns the directory, or None
    where ``directory`` is None or cannot be created (a note goes to stderr)."""
    _enabled["chosen"] = True
    if directory is None:
        return None
    directory = os.path.abspath(os.path.expanduser(directory))
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as err:
        print(f"note: compilation cache off ({directory}: {err.strerror or err})", file=sys.stderr)
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", directory)
    # JAX's defaults skip programs compiled in under a second; DIT's small ones add up at start-up.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _enabled["directory"] = directory
    return directory


def directory() -> str | None:
    """The directory :func:`enable` turned on in this process, or None."""
    return _enabled["directory"]


def chosen() -> bool:
    """Whether this process has already turned the cache on or off (:func:`enable`, :func:`from_args`)."""
    return _enabled["chosen"]


@functools.cache
def _source_digest() -> str:
    """A digest of this package's Python source and of what else decides how JAX traces it."""
    import jax
    import jaxlib

    digest = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    digest.update(
        repr(
            (
                jax.__version__,
                jaxlib.__version__,
                jax.default_backend(),
                jax.config.jax_enable_x64,
                jax.config.jax_default_matmul_precision,
            )
        ).encode()
    )
    return digest.hexdigest()


def _key(name: str, parts) -> str:
    return f"{name}-" + hashlib.sha256(f"{_source_digest()}|{parts!r}".encode()).hexdigest()[:32]


def write_atomically(path: str, data: bytes) -> None:
    """Writes ``data`` to ``path`` through a temporary file, so a reader never sees half of it."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    handle, staging = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".staging-")
    try:
        with os.fdopen(handle, "wb") as f:
            f.write(data)
        os.chmod(staging, 0o644)  # as XLA's own entries: readable by whoever shares the cache
        os.replace(staging, path)
    except OSError:
        if os.path.exists(staging):
            os.remove(staging)


def memo(name: str, parts, compute):
    """``compute()``, a JSON-able value that depends only on this package's code and ``parts`` (a value with a
    stable ``repr``, such as a frozen config), kept under ``DIR/memo/`` while the cache is on."""
    if directory() is None:
        return compute()
    path = os.path.join(directory(), "memo", _key(name, parts) + ".json")
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        pass
    value = compute()
    write_atomically(path, json.dumps(value).encode())
    return value


def call(name: str, fn, parts, *args):
    """``fn(*args)``, where ``fn`` is a function of arrays (pytrees of arrays) that JAX can jit and ``parts``
    (a value with a stable ``repr``, such as a frozen config) holds whatever else ``fn`` depends on.

    While the cache is on, the program is traced once per ``parts`` and argument shapes across processes:
    exported (:mod:`jax.export`) to ``DIR/exported/`` on first use and read back after, so a later process
    compiles it from XLA's cache without running ``fn``'s Python. The result is the same either way (the same
    program). With the cache off, ``fn`` is called as it is; where a program cannot be exported, it is jitted.
    """
    import jax

    if directory() is None:
        return fn(*args)
    leaves, tree = jax.tree_util.tree_flatten(args)
    signature = (parts, str(tree), tuple((tuple(x.shape), str(x.dtype)) for x in leaves))
    key = _key(name, signature)
    program = _programs.get(key)
    if program is None:
        program = _programs[key] = _load_or_export(key, fn, args)
    return program(*args)


def _load_or_export(key: str, fn, args):
    import jax
    from jax import export

    path = os.path.join(directory(), "exported", key + ".bin")
    try:
        with open(path, "rb") as f:
            return jax.jit(export.deserialize(bytearray(f.read())).call)
    except Exception:  # absent, damaged, or no serializer: export it afresh
        pass
    jitted = jax.jit(fn)
    try:
        serialized = bytes(export.export(jitted)(*args).serialize())
        write_atomically(path, serialized)
    except Exception:  # cannot export: jit as usual (an error of fn's own comes back from the call)
        return jitted
    # The program read back, as a later process reads it: the fresh export compiles to a program that XLA's
    # cache files under another key, so every later process would compile its own once more.
    return jax.jit(export.deserialize(bytearray(serialized)).call)


def from_args(args: argparse.Namespace) -> str | None:
    """:func:`enable` as :func:`add_arguments`' flags say."""
    if args.no_compile_cache:
        _enabled["chosen"] = True
        return None
    return enable(args.compile_cache or default_dir())
