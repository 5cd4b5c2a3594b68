import os
import pathlib
import subprocess
import sys

import pytest

from dit_jax import compile_cache

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
    command = [sys.executable, "-m", "dit_jax.cli", "examples/chair_src.ply", "examples/chair_tgt.pcd",
               "--points", "256", "--no-verdict-status", "--verdict", "fitness", *cache_args]  # one direction
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()[:4]  # the matrix


def test_a_second_dit_register_reuses_the_first_ones_programs(tmp_path):
    """The first call fills the cache; the second finds every program there (adds no entry) and prints the
    same transform. Times: docs/benchmarks.md."""
    cache = tmp_path / "xla"
    first = _register(["--compile-cache", str(cache)])
    entries = set(os.listdir(cache))
    assert len(entries) >= 3  # the registration and the small programs around it
    second = _register(["--compile-cache", str(cache)])
    assert set(os.listdir(cache)) == entries
    assert second == first


def test_no_compile_cache_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "xla"))
    _register(["--no-compile-cache"])
    assert not (tmp_path / "xla").exists()
