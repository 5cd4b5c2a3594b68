"""JAX's persistent compilation cache for the command-line tools (``dit-register``, ``train.py``, ``evaluate.py``).

XLA compiles DIT's registration for each config and cloud size; on a CPU that takes longer than the
registration itself. With the cache on, a second process with the same shapes loads the compiled program
from disk instead (timings: docs/benchmarks.md).

The directory, in order: ``--compile-cache DIR``; the environment variable ``DIT_JAX_COMPILE_CACHE``;
``$XDG_CACHE_HOME/dit-jax/xla``, else ``~/.cache/dit-jax/xla``. ``--no-compile-cache`` (or the variable set
to ``off``) turns it off. A directory that cannot be created leaves the cache off with a note on stderr:
caching only saves time, so it never stops a run.
"""

from __future__ import annotations

import argparse
import os
import sys

#: Overrides the default directory; "off" turns the cache off.
ENV_VAR = "DIT_JAX_COMPILE_CACHE"


def default_dir() -> str | None:
    """The directory used when no flag says otherwise; None where the environment turns the cache off."""
    chosen = os.environ.get(ENV_VAR)
    if chosen:
        return None if chosen.lower() == "off" else chosen
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "dit-jax", "xla")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--compile-cache DIR`` and ``--no-compile-cache``."""
    parser.add_argument("--compile-cache", default=None, metavar="DIR",
                        help=f"keep compiled XLA programs here, so the next run starts without compiling "
                             f"(default: ${ENV_VAR}, else ~/.cache/dit-jax/xla)")
    parser.add_argument("--no-compile-cache", action="store_true", help="compile afresh every run")


def enable(directory: str | None) -> str | None:
    """Points JAX's persistent compilation cache at ``directory`` (created if missing) and caches every
    program, however quick to compile. Call before the first compilation. Returns the directory, or None
    where ``directory`` is None or cannot be created (a note goes to stderr)."""
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
    return directory


def from_args(args: argparse.Namespace) -> str | None:
    """:func:`enable` as :func:`add_arguments`' flags say."""
    if args.no_compile_cache:
        return None
    return enable(args.compile_cache or default_dir())
