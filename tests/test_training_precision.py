"""train_precision="auto": the train step's precision chosen by timing both on this machine."""

import dataclasses
import json

import numpy as np
import pytest
from conftest import ROOT

from dit_jax import training
from dit_jax.network import compile_cache
from dit_jax.training import precision

TINY = dataclasses.replace(
    training.load_config(ROOT / "configs" / "tiny.py"), max_steps=2, ckpt_every=2, eval_every=2, val_pairs=4
)


def _batch(config):
    rng = np.random.default_rng(0)
    src = rng.uniform(-1, 1, (config.batch_size, config.n_points, 3)).astype(np.float32)
    return {
        "src": src,
        "tgt": src[:, ::-1] + 0.1,
        "R": np.tile(np.eye(3, dtype=np.float32), (config.batch_size, 1, 1)),
        "t": np.full((config.batch_size, 3), 0.1, np.float32),
    }


def _fake_timer(seconds, calls):
    """A timer that reports ``seconds[precision]`` and records which precisions it was asked for."""

    def timer(config, optimizer, mesh, batch, steps):
        calls.append(config.train_precision)
        return seconds[config.train_precision]

    return timer


@pytest.mark.parametrize(
    ("float32_s", "bfloat16_s", "expected"),
    [(2.0, 1.0, "bfloat16"), (1.15, 1.0, "bfloat16"), (1.1, 1.0, None), (1.0, 1.2, None)],
)
def test_bfloat16_is_chosen_only_beyond_the_margin(float32_s, bfloat16_s, expected):
    assert precision.decide(float32_s, bfloat16_s) == expected


def test_the_choice_is_measured_once_per_machine_and_shape(tmp_path, monkeypatch):
    monkeypatch.setitem(compile_cache._enabled, "directory", str(tmp_path))
    config = dataclasses.replace(TINY, train_precision="auto")
    optimizer, mesh = training.make_optimizer(config, 10), training.make_mesh()
    calls = []
    timer = _fake_timer({None: 3.0, "bfloat16": 1.5}, calls)

    first = precision.choose(config, optimizer, mesh, _batch(config), timer=timer)
    assert (first.precision, first.cached, first.speedup) == ("bfloat16", False, 2.0)
    assert calls == [None, "bfloat16"]

    again = precision.choose(config, optimizer, mesh, _batch(config), timer=timer)
    assert (again.precision, again.cached) == ("bfloat16", True) and len(calls) == 2
    assert "bfloat16" in again.describe() and "2.00x" in again.describe()

    # Another cloud size, or another XLA ISA limit, is another measurement.
    bigger = dataclasses.replace(config, n_points=2 * config.n_points)
    precision.choose(bigger, optimizer, mesh, _batch(bigger), timer=timer)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX2")
    precision.choose(config, optimizer, mesh, _batch(config), timer=timer)
    assert len(calls) == 6


def test_a_bfloat16_step_that_fails_leaves_float32(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(compile_cache._enabled, "directory", str(tmp_path))
    config = dataclasses.replace(TINY, train_precision="auto")

    def timer(config, optimizer, mesh, batch, steps):
        if config.train_precision == "bfloat16":
            raise RuntimeError("no bfloat16 products here")
        return 1.0

    optimizer, mesh = training.make_optimizer(config, 10), training.make_mesh()
    for cached in (False, True):  # the failure is remembered like a timing
        choice = precision.choose(config, optimizer, mesh, _batch(config), timer=timer)
        assert (choice.precision, choice.cached, choice.speedup) == (None, cached, 0.0)
    assert "bfloat16 failed here (RuntimeError: no bfloat16 products here)" in capsys.readouterr().err


def test_auto_cannot_build_a_step_before_it_is_chosen():
    auto = dataclasses.replace(TINY, train_precision="auto")
    with pytest.raises(ValueError, match="chosen when a run starts"):
        auto.train_model_config()


def test_time_steps_times_a_real_step():
    optimizer, mesh = training.make_optimizer(TINY, 10), training.make_mesh()
    seconds = precision.time_steps(TINY, optimizer, mesh, _batch(TINY), steps=1)
    assert 0 < seconds < 60


def test_a_run_records_the_precision_it_chose(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(compile_cache._enabled, "directory", str(tmp_path / "cache"))  # not the suite's cache
    calls = []
    monkeypatch.setattr(precision, "time_steps", _fake_timer({None: 1.0, "bfloat16": 0.5}, calls))
    config = dataclasses.replace(TINY, train_precision="auto", validate_at_start=False)
    training.train(config, str(tmp_path / "run"), progress=False)
    assert calls == [None, "bfloat16"]
    saved = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert saved["train_precision"] == "bfloat16"
    assert "train precision: bfloat16" in capsys.readouterr().out
