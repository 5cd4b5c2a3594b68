import json
import os
import pathlib
import subprocess
import sys

import pytest

from dit_jax.network import compile_cache

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_default_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "mine"))
    assert compile_cache.default_dir() == str(tmp_path / "mine")
    monkeypatch.setenv(compile_cache.ENV_VAR, "off")
    assert compile_cache.default_dir() is None
    monkeypatch.delenv(compile_cache.ENV_VAR)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.default_dir() == str(tmp_path / "xdg" / "dit-jax" / "xla")


def test_a_directory_that_cannot_be_made_leaves_the_cache_off(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert compile_cache.enable(str(blocker / "xla")) is None
    assert "compilation cache off" in capsys.readouterr().err


def _register(cache_args):
    command = [
        sys.executable,
        "-m",
        "dit_jax.cli.register",
        "examples/chair_src.ply",
        "examples/chair_tgt.pcd",
        "--points",
        "256",
        "--no-verdict-status",
        "--verdict",
        "fitness",
        *cache_args,
    ]  # one direction
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()[:4]  # the matrix


def test_a_second_dit_register_reuses_the_first_ones_programs(tmp_path):
    """The first call fills the cache; the second finds every program there (adds no entry) and prints the
    same transform. Times: docs/benchmarks.md."""
    cache = tmp_path / "xla"
    first = _register(["--compile-cache", str(cache)])
    entries = {p.relative_to(cache) for p in cache.rglob("*")}
    assert len(entries) >= 3  # the registration and the small programs around it
    assert [p.name for p in (cache / "exported").iterdir() if p.name.startswith("register-")], (
        "the network's traced program is kept too"
    )
    moved = tmp_path / "moved.ply"
    second = _register(["--compile-cache", str(cache), "--out", str(moved)])
    assert {p.relative_to(cache) for p in cache.rglob("*")} == entries
    assert second == first
    # The console script leaves without Python's shutdown (dit_jax.cli.files.console_script): its output is whole.
    from dit_jax import io

    assert io.read(str(moved)).shape == io.read("examples/chair_src.ply").shape


def test_no_compile_cache_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "xla"))
    _register(["--no-compile-cache"])
    assert not (tmp_path / "xla").exists()


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    """:func:`compile_cache.call` and :func:`compile_cache.memo` pointed at a fresh directory, with nothing
    loaded in this process yet (as in a new process); JAX's own cache settings are left alone."""
    monkeypatch.setitem(compile_cache._enabled, "directory", str(tmp_path))
    monkeypatch.setattr(compile_cache, "_programs", {})
    return tmp_path


def test_call_traces_a_program_once_across_processes(cache_dir, monkeypatch):
    import jax.numpy as jnp

    traced = []

    def fn(params, x):
        traced.append(x.shape)  # runs only while JAX traces fn
        return jnp.tanh(x @ params["w"]) * params["scale"]

    params = {"w": jnp.eye(3) * 2.0, "scale": jnp.asarray(0.5)}
    x = jnp.arange(12.0).reshape(4, 3) / 10
    expected = jnp.tanh(x @ params["w"]) * 0.5
    assert jnp.allclose(compile_cache.call("f", fn, "v1", params, x), expected)
    assert traced == [(4, 3)] and len(list((cache_dir / "exported").iterdir())) == 1
    assert jnp.allclose(compile_cache.call("f", fn, "v1", params, x + 1), jnp.tanh((x + 1) @ params["w"]) * 0.5)
    assert len(traced) == 1, "a second call in the same process reuses the program"

    monkeypatch.setattr(compile_cache, "_programs", {})  # a new process, as far as the cache can tell
    assert jnp.allclose(compile_cache.call("f", fn, "v1", params, x), expected)
    assert len(traced) == 1, "read back from the directory, not traced again"

    compile_cache.call("f", lambda p, x: fn(p, x) + 1, "v2", params, x)  # other settings: another program
    compile_cache.call("f", fn, "v1", params, jnp.ones((5, 3)))  # another shape: another program
    assert traced == [(4, 3), (4, 3), (5, 3)] and len(list((cache_dir / "exported").iterdir())) == 3


def test_call_recovers_from_a_damaged_program_and_runs_without_a_cache(cache_dir, monkeypatch):
    import jax.numpy as jnp

    fn = lambda x: x * 3.0  # noqa: E731
    x = jnp.arange(4.0)
    compile_cache.call("g", fn, None, x)
    (program,) = (cache_dir / "exported").iterdir()
    program.write_bytes(b"not a program")
    monkeypatch.setattr(compile_cache, "_programs", {})
    assert jnp.allclose(compile_cache.call("g", fn, None, x), x * 3.0)
    assert program.read_bytes() != b"not a program", "exported afresh"
    monkeypatch.setitem(compile_cache._enabled, "directory", None)
    assert jnp.allclose(compile_cache.call("g", fn, None, x), x * 3.0)


def test_memo_computes_once_per_parts(cache_dir):
    computed = []

    def compute():
        computed.append(1)
        return {"a": [1, 2]}

    assert compile_cache.memo("m", ("config", 1), compute) == {"a": [1, 2]}
    assert compile_cache.memo("m", ("config", 1), compute) == {"a": [1, 2]}
    assert len(computed) == 1
    compile_cache.memo("m", ("config", 2), compute)
    assert len(computed) == 2


# A Python user's session: load the shipped weights, register the README's pair, and say what was imported.
_API_SESSION = """
import json, sys
from dit_jax import io, registration
cache = sys.argv[1]
model = registration.load(compile_cache={"default": True, "off": False}.get(cache, cache))
result = model.register(io.read("examples/chair_src.ply"), io.read("examples/chair_tgt.pcd"))
heavy = ("orbax", "open3d", "matplotlib", "tensorflow_datasets", "optax", "tensorflow", "flax", "scipy.spatial")
print(json.dumps({"matrix": result.matrix.round(6).tolist(), "imported": sorted(set(heavy) & set(sys.modules))}))
"""


def _api_session(cache: str, env: dict) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", _API_SESSION, cache], cwd=ROOT, capture_output=True, text=True, timeout=600, env=env
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


def test_the_python_api_keeps_programs_and_weights_in_the_cache_by_default(tmp_path):
    """registration.load() turns the cache on as the command-line tools do: the first session fills the
    default directory ($DIT_JAX_COMPILE_CACHE here) with programs and the weights' plain copy; the next one
    registers the same pair to the same matrix without importing orbax (or Open3D, matplotlib, TFDS, optax,
    Flax, or scipy's k-d tree: small clouds' ICP queries small_gicp's)."""
    env = {k: v for k, v in os.environ.items() if k not in ("DIT_JAX_COMPILE_CACHE", "DIT_JAX_TEST_XLA_CACHE")}
    env["DIT_JAX_COMPILE_CACHE"] = str(tmp_path / "default")
    first = _api_session("default", env)
    cache = tmp_path / "default"
    assert list((cache / "params").glob("*.npz")) and list((cache / "exported").glob("register-*"))
    second = _api_session("default", env)
    assert second["matrix"] == first["matrix"] and second["imported"] == []


def test_load_turns_the_cache_on_unless_told_not_to_or_one_is_on(monkeypatch, tmp_path):
    from dit_jax.pipeline import registration

    turned_on = []
    monkeypatch.setattr(compile_cache, "enable", lambda directory: turned_on.append(directory))
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "env"))
    for argument in (False, tmp_path / "mine", True):  # each the process's first choice
        monkeypatch.setitem(compile_cache._enabled, "chosen", False)
        registration.load(compile_cache=argument)
    assert turned_on == [None, str(tmp_path / "mine"), str(tmp_path / "env")]
    monkeypatch.setitem(compile_cache._enabled, "chosen", True)  # a tool's --no-compile-cache, or a first load
    registration.load(compile_cache=tmp_path / "other")
    assert len(turned_on) == 3
