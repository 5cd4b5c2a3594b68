import dataclasses
import json
import logging
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_rotation, shared_point_pairs

from dit_jax import training
from dit_jax.evaluators import metrics
from dit_jax.network import losses, model

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY_RECIPE = training.load_config(ROOT / "configs" / "tiny.py")
# No validation before the first step: the run that validates at step 0 (the default) is the resumed one.
TINY = dataclasses.replace(TINY_RECIPE, max_steps=12, ckpt_every=4, eval_every=6, val_pairs=4, validate_at_start=False)
#: train.py's arguments for TINY but validate_at_start (the default, True).
TINY_ARGS_VALIDATING = [
    "--config",
    str(ROOT / "configs" / "tiny.py"),
    "--config.max_steps=12",
    "--config.ckpt_every=4",
    "--config.eval_every=6",
    "--config.val_pairs=4",
]
#: train.py's arguments for TINY.
TINY_ARGS = [*TINY_ARGS_VALIDATING, "--config.validate_at_start=False"]


@pytest.fixture(scope="module")
def prepared(prepared_dir):
    return prepared_dir


def _params(workdir):
    return training.export_params(str(workdir), str(pathlib.Path(workdir) / "exported"))


def _equal_trees(a, b):
    return jax.tree.all(jax.tree.map(lambda x, y: bool(np.array_equal(np.asarray(x), np.asarray(y))), a, b))


def _step_setup(config, prepared):
    train_ds, _ = training.make_datasets(config, prepared)
    # The optimizer train() builds for this config: the step compiles to the program tiny_run's does, so
    # one of them finds it in the session's compilation cache.
    optimizer = training.make_optimizer(config, config.max_steps)
    mesh = training.make_mesh()
    state = training.replicate(training.init_state(config, optimizer), mesh)
    return train_ds, mesh, state, training.make_train_step(config, optimizer, mesh)


def test_a_few_dozen_steps_learn_to_match_held_out_pairs(prepared):
    """Learning, not a falling loss: fresh training pairs at every step, judged on pairs of held-out shapes.

    The cpu network with one PFT block at 128 points, one registration iteration unrolled (the network alone
    is what is judged; half the compilation of two), 30 steps, seed 0. This seed starts with its temperature
    clamped at 1/100: before the clamp let gradients back into its range, the two-block network's held-out match
    accuracy fell from 0.72 to 0.44 here (rotation error of the network alone 17.6 -> 21.3 degrees). Now it
    goes from 0.74 to 0.96 and from 15.7 to 0.8 degrees (docs/training.md has every seed of the quick run).
    """
    from dit_jax.data import prefetch

    steps = 30
    from dit_jax.network import configs

    base = dataclasses.replace(
        TINY_RECIPE, model=configs.cpu().replace(n_blocks=1), settings=(), n_points=128, max_steps=steps, train_iters=1
    )
    optimizer = training.make_optimizer(base, steps)
    mesh = training.make_mesh()
    step = training.make_train_step(base, optimizer, mesh)
    train_ds, val_ds = training.make_datasets(base, prepared)
    state = training.replicate(training.init_state(base, optimizer), mesh)
    before = training.validate(state.params, val_ds, base.model_config(), 16)
    for _, batch in zip(range(steps), prefetch.batches(train_ds, base.batch_size, epoch=0)):
        state, _ = step(state, training.shard_batch(batch, mesh))
    assert int(state.step) == steps and int(state.skipped) == 0
    after = training.validate(state.params, val_ds, base.model_config(), 16)
    summary = f"{before} -> {after}"
    assert after["network_match_accuracy"] >= max(0.85, before["network_match_accuracy"] + 0.15), summary
    assert after["network_rotation_error"] <= min(3.0, 0.2 * before["network_rotation_error"]), summary


def test_non_finite_batches_are_skipped_not_applied(prepared):
    train_ds, mesh, state, step = _step_setup(TINY, prepared)
    good = train_ds.batch(np.arange(4), epoch=0)
    bad = dict(good, src=good["src"].copy())
    bad["src"][1, 3, 0] = np.nan
    before = jax.device_get(state.params)
    state, out = step(state, training.shard_batch(bad, mesh))
    assert not bool(out["finite"]) and int(state.skipped) == 1 and int(state.step) == 1
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(a, np.asarray(b)), before, state.params)
    state, out = step(state, training.shard_batch(good, mesh))
    assert bool(out["finite"]) and int(state.skipped) == 1
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(state.params))
    changed = jax.tree.map(lambda a, b: not np.array_equal(a, np.asarray(b)), before, state.params)
    assert any(jax.tree.leaves(changed))


class TinyRun(NamedTuple):
    workdir: pathlib.Path
    result: dict
    lowered: list[str]  # the programs lowered while it trained, by name ("jit(step)", ...)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, prepared):
    """One TINY run of 12 steps (checkpoints at 4, 8 and 12), trained in this process into a relative
    workdir, as `python train.py` gets by default, with the names of the programs it lowered. Several tests
    read it, so the suite trains it once."""
    directory = tmp_path_factory.mktemp("tiny")
    lowered = []
    handler = logging.Handler(logging.DEBUG)
    handler.emit = lambda record: lowered.append(record.getMessage().split()[1])
    pxla = logging.getLogger("jax._src.interpreters.pxla")  # logs "Compiling NAME ..." for every lowering
    level = pxla.level
    # Validation's program is lowered here, whatever ran before in this process (the train step is made
    # afresh by train()); clearing only this function's cache spares the other tests' programs.
    model.register.clear_cache()
    pxla.addHandler(handler)
    pxla.setLevel(logging.DEBUG)
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.chdir(directory)
            result = training.train(TINY, "run", prepared_dir=prepared, progress=False)
    finally:
        pxla.removeHandler(handler)
        pxla.setLevel(level)
    return TinyRun(directory / "run", result, lowered)


def test_training_writes_checkpoints_and_metrics(tiny_run, prepared):
    workdir, result, lowered = tiny_run
    assert result["step"] == 12 and result["skipped"] == 0
    assert sorted(os.listdir(workdir / "checkpoints")) == ["12", "4", "8"]
    assert os.listdir(workdir / "best")
    lines = (workdir / "metrics.jsonl").read_text().splitlines()
    assert any('"split": "val"' in line for line in lines) and len(lines) >= 12
    # A mix of two settings whose clouds differ in size (64 and 51 points), thinned to one size: one train
    # step and one validation program for both settings, each with its own GMCCE threshold.
    assert lowered.count("jit(step)") == 1 and lowered.count("jit(register)") == 1, lowered
    assert set(TINY.settings) <= {key.split("/")[0] for key in result["val"] if "/" in key}
    from dit_jax.network import checkpoint

    _, config = checkpoint.restore(result["model"])
    assert config == TINY.model_config()
    # Starting again in the same directory without --resume is refused, never a silent restart.
    with pytest.raises(training.TrainCheckpointError, match="pass --resume"):
        training.train(TINY, str(workdir), prepared_dir=prepared, progress=False)


def test_a_lease_brings_its_compilation_cache_back_within_the_tools_file_limit(tmp_path):
    """device_stage's xla_cache.tar keeps the largest entries (the train steps) that fit the limit, and the
    next lease's --cache-from unpacks them where the persistent cache looks."""
    import device_stage

    cache = tmp_path / "cache"
    cache.mkdir()
    for name, size in (
        ("jit_step-a-cache", 600),
        ("jit_step-b-cache", 500),
        ("jit_register-c-cache", 300),
        ("jit_sign-d-cache", 50),
    ):
        (cache / name).write_bytes(bytes(size))
    device_stage._cache_out(str(cache), str(tmp_path / "xla_cache.tar"), limit=1000)
    device_stage._cache_in(str(tmp_path / "xla_cache.tar"), str(tmp_path / "next"))
    assert sorted(os.listdir(tmp_path / "next")) == ["jit_register-c-cache", "jit_sign-d-cache", "jit_step-a-cache"]
    assert (tmp_path / "next" / "jit_step-a-cache").read_bytes() == bytes(600)


def test_a_run_can_skip_the_validation_before_its_first_step(tmp_path, tiny_run):
    """validate_at_start=False (tiny_run's): no step-0 validation (what a short GPU lease cannot afford to
    compile), the later ones still run. A run stopped before any validation still leaves weights:
    tools/device_stage.py then bundles its latest checkpoints, and export_params reads them."""
    import tarfile

    import device_stage

    records = [json.loads(line) for line in (tiny_run.workdir / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if r["split"] == "val"] == [6, 12]

    never_validated = tmp_path / "stopped"
    shutil.copytree(tiny_run.workdir, never_validated)
    shutil.rmtree(never_validated / "best")
    device_stage._bundle(str(never_validated), str(tmp_path / "stopped.tar"))
    with tarfile.open(tmp_path / "stopped.tar") as tar:
        names = tar.getnames()
        tar.extractall(tmp_path / "back", filter="data")
    assert any(n.startswith("checkpoints/12") for n in names) and not any(n.startswith("best") for n in names)
    from dit_jax.network import checkpoint

    assert (
        checkpoint.read_extra(training.export_params(str(tmp_path / "back"), str(tmp_path / "model")))["chosen_by"]
        == "checkpoints"
    )
    latest = checkpoint.read_extra(training.export_params(str(tiny_run.workdir), str(tmp_path / "end"), latest=True))
    assert (latest["chosen_by"], latest["step"]) == ("checkpoints", 12)
    device_stage._bundle(str(tiny_run.workdir), str(tmp_path / "validated.tar"))
    with tarfile.open(tmp_path / "validated.tar") as tar:
        assert any(n.startswith("best/") for n in tar.getnames())
        assert not any(n.startswith("checkpoints") for n in tar.getnames())


def test_resume_after_kill_9_ends_with_the_same_params(tmp_path, prepared, tiny_run):
    """The run killed after its step-4 checkpoint and resumed ends at tiny_run's parameters (the same run,
    uninterrupted, and without the step-0 validation this one makes: validating changes no step)."""
    workdir = tmp_path / "killed"
    cmd = [
        sys.executable,
        str(ROOT / "train.py"),
        *TINY_ARGS_VALIDATING,
        "--workdir",
        str(workdir),
        "--no-progress",
        "--prepared-dir",
        prepared,
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while time.time() < deadline and not (workdir / "checkpoints" / "4").exists():
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (workdir / "checkpoints" / "4").exists(), "the run made no checkpoint before the kill"
    # Resumed by train.py's main in this process: the same command line, without a second interpreter's start.
    import train

    assert train.main([*cmd[2:], "--resume"]) == 0
    (step, resumed_params), (whole_step, whole_params) = _last_params(workdir), _last_params(tiny_run.workdir)
    assert step == whole_step == 12 and _equal_trees(resumed_params, whole_params)
    records = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    assert sorted(r["step"] for r in records if r["split"] == "val") == [0, 6, 12]


def test_damaged_checkpoint_gives_a_clear_error(tmp_path, prepared, tiny_run):
    # A copy of a finished run cut back to its step-4 checkpoint, then damaged.
    config = dataclasses.replace(TINY, max_steps=4)
    shutil.copytree(tiny_run.workdir, tmp_path / "run")
    for step in ("8", "12"):
        shutil.rmtree(tmp_path / "run" / "checkpoints" / step)
    for f in (tmp_path / "run" / "checkpoints" / "4" / "state").rglob("*"):
        if f.is_file() and f.stat().st_size > 0 and "metadata" not in f.name:
            f.write_bytes(b"\0" * 7)
    with pytest.raises(training.TrainCheckpointError, match="does not restore"):
        training.train(
            dataclasses.replace(config, max_steps=8),
            str(tmp_path / "run"),
            resume=True,
            prepared_dir=prepared,
            progress=False,
        )
    other = dataclasses.replace(config, model=config.model.replace(n_blocks=2))
    with pytest.raises(training.TrainCheckpointError, match="made for model"):
        training.train(other, str(tmp_path / "run"), resume=True, prepared_dir=prepared, progress=False)


def test_a_checkpoint_with_the_optimiser_state_per_array_says_how_to_go_on(tmp_path, prepared, tiny_run):
    """A train state saved with the optimiser's state per parameter array (as before it became one vector)
    does not resume; the error says so in one line and how to start from its weights, which still export."""
    import orbax.checkpoint as ocp

    shutil.copytree(tiny_run.workdir, tmp_path / "run")
    manager = ocp.CheckpointManager(os.path.abspath(tmp_path / "run" / "checkpoints"), item_names=("state", "meta"))
    raw = manager.restore(12, args=ocp.args.Composite(state=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore()))
    optimizer = training.make_optimizer(TINY, TINY.max_steps)
    per_array = training.TrainState(
        step=raw.state["step"],
        params=raw.state["params"],
        opt_state=optimizer.init(raw.state["params"]),
        rng=raw.state["rng"],
        skipped=raw.state["skipped"],
    )
    shutil.rmtree(tmp_path / "run" / "checkpoints" / "12")  # saved again in the older layout
    manager.reload()
    training.checkpoints._save(manager, per_array, raw.meta)
    with pytest.raises(training.TrainCheckpointError, match="per parameter array") as error:
        training.train(
            dataclasses.replace(TINY, max_steps=16),
            str(tmp_path / "run"),
            resume=True,
            prepared_dir=prepared,
            progress=False,
        )
    assert "\n" not in str(error.value) and "--config.init_from" in str(error.value)
    from dit_jax.network import checkpoint

    checkpoint_params, _ = checkpoint.restore(
        training.export_params(str(tmp_path / "run"), str(tmp_path / "model"), latest=True)
    )
    assert _equal_trees(checkpoint_params, raw.state["params"])


def test_losses_vanish_at_the_truth():
    eye, zero = jnp.eye(3), jnp.zeros(3)
    assert float(losses.transformation_loss(eye, zero, eye, zero)) == 0.0
    assert float(losses.cycle_loss(eye, zero, eye, zero)) == 0.0
    src = jnp.asarray(np.random.default_rng(0).normal(size=(10, 3)), jnp.float32)
    labels = losses.match_labels(src, src + 1.0, jnp.arange(10), eye, jnp.ones(3))
    np.testing.assert_array_equal(np.asarray(labels), 1.0)
    wrong = losses.match_labels(src, src + 1.0, jnp.roll(jnp.arange(10), 1), eye, jnp.ones(3))
    assert float(wrong.mean()) < 0.5
    assert float(losses.discrimination_loss(jnp.array([1.0, 0.0]), jnp.array([1.0, 0.0]))) < 1e-5


def test_correspondence_loss_pulls_soft_matches_onto_true_positions_where_a_counterpart_exists():
    rng = np.random.default_rng(0)
    src = jnp.asarray(rng.normal(size=(12, 3)), jnp.float32)
    rotation = jnp.asarray(random_rotation(rng), jnp.float32)
    truth = src @ rotation.T + 0.5
    tgt = truth + 0.01  # every true position has a target point 0.017 away
    assert float(losses.correspondence_loss(truth, src, tgt, rotation, jnp.full(3, 0.5), radius=0.05)) == 0.0
    off = truth.at[0].add(jnp.array([0.3, 0.0, 0.0]))
    np.testing.assert_allclose(
        float(losses.correspondence_loss(off, src, tgt, rotation, jnp.full(3, 0.5), radius=0.05)), 0.09 / 12, rtol=1e-5
    )
    # A source point whose true position has no target point near (cropped away) is not pulled anywhere.
    cropped = tgt.at[0].add(5.0)
    assert float(losses.correspondence_loss(off, src, cropped, rotation, jnp.full(3, 0.5), radius=0.05)) < 1e-10
    # No counterpart at all: 0, not NaN.
    assert float(losses.correspondence_loss(off, src, tgt + 10.0, rotation, jnp.full(3, 0.5), radius=0.05)) == 0.0
    # In the total only with a weight (0: the authors' objective, unchanged), discounted per iteration.
    eye = jnp.broadcast_to(jnp.eye(3), (2, 3, 3))
    its = model.Iterations(
        rotation=eye,
        translation=jnp.zeros((2, 3)),
        rotation_ab=eye,
        translation_ab=jnp.zeros((2, 3)),
        rotation_ba=eye,
        translation_ba=jnp.zeros((2, 3)),
        soft_weights=jnp.full((2, 12), 0.5),
        correspondences=jnp.zeros((2, 12), jnp.int32),
        temperature=jnp.ones(2),
        soft_targets=jnp.stack([off, off]),
    )
    dit_loss = jax.jit(losses.dit_loss, static_argnames=("match_radius", "correspondence_weight"))
    plain, plain_terms = dit_loss(its, src, tgt, rotation, jnp.full(3, 0.5), match_radius=0.05)
    weighted, terms = dit_loss(its, src, tgt, rotation, jnp.full(3, 0.5), match_radius=0.05, correspondence_weight=2.0)
    assert "correspondence" not in plain_terms
    np.testing.assert_allclose(float(terms["correspondence"]), 1.9 * 0.09 / 12, rtol=1e-5)
    np.testing.assert_allclose(float(weighted - plain), 2.0 * 1.9 * 0.09 / 12, rtol=1e-4)


def test_train_cli_reads_a_recipe_file_and_its_field_overrides(capsys):
    """``--config FILE`` and ``--config.FIELD=VALUE`` (``--config.model.FIELD`` for the network): typed, and
    unknown fields or values of the wrong type end in one line and status 2."""
    import train

    _, config, workdir = train.parse(
        [
            "--config",
            str(ROOT / "configs" / "tiny.py"),
            "--config.lr=0.5",
            "--config.model.n_blocks=2",
            "--config.max_steps=7",
        ]
    )
    assert config.lr == 0.5 and config.model.n_blocks == 2 and config.max_steps == 7 and workdir == "runs/tiny-mix"
    assert dataclasses.replace(config, lr=TINY_RECIPE.lr, max_steps=None, model=TINY_RECIPE.model) == TINY_RECIPE, (
        "nothing else moves"
    )
    _, config, _ = train.parse(
        [
            "--config",
            str(ROOT / "configs" / "tiny.py"),
            "--config.differentiable=false",
            "--config.settings=('clean', 'independent_clean')",
        ]
    )
    assert config.differentiable is False and config.settings == ("clean", "independent_clean")
    _, default, workdir = train.parse([])
    assert default == training.load_config(ROOT / "configs" / "quick.py") and workdir == "runs/quick-clean"
    with pytest.raises(SystemExit) as exit_info:
        train.parse(["--help"])
    assert exit_info.value.code == 0 and "--config.model.FIELD=VALUE" in capsys.readouterr().out
    for bad in ("--config.bogus=1", "--config.lr=fast", "--config.model.n_blocks=two", "--preset=tiny"):
        with pytest.raises(SystemExit) as exit_info:
            train.parse([bad])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and err.startswith("train.py: error:") and err.count("\n") == 1, bad


def test_resume_reads_the_config_saved_in_the_workdir(tmp_path):
    import train

    config = dataclasses.replace(TINY, lr=0.123, model=TINY.model.replace(n_blocks=2))
    (tmp_path / "train_config.json").write_text(json.dumps(config.to_json()))
    _, resumed, _ = train.parse(["--workdir", str(tmp_path), "--resume"])
    assert resumed == config
    _, explicit, _ = train.parse(
        ["--workdir", str(tmp_path), "--resume", "--config", str(ROOT / "configs" / "tiny.py")]
    )
    assert explicit == TINY_RECIPE


def test_every_recipe_file_loads_and_a_checkpoint_reads_back_its_config(tmp_path, tiny_run):
    """Every file in configs/ (the shipped weights' runs included) gives a valid TrainConfig; a trained model
    records the config it was trained with, readable back into the same type; a record that names the
    model by preset (as the shipped weights' older runs do) reads as that preset with its changes."""
    from dit_jax.network import checkpoint, configs
    from dit_jax.training.descriptor import DescriptorTrainConfig

    for path in sorted((ROOT / "configs").rglob("*.py")):
        kind = DescriptorTrainConfig if path.name == "features.py" else training.TrainConfig
        assert isinstance(training.load_config(path), kind), path
    recorded = checkpoint.read_extra(tiny_run.result["model"])["train_config"]
    assert training.TrainConfig.from_json(recorded) == TINY
    legacy = dict(TINY.to_json(), model="cpu", model_overrides=[["n_blocks", 1]])
    assert training.TrainConfig.from_json(legacy).model == configs.cpu("clean").replace(n_blocks=1)


def test_the_shipped_recipe_files_are_what_trained_the_shipped_weights():
    """configs/shipped/runN.py gives the config the shipped weights record for run N (the last run in
    ``train_config``, each earlier one under ``trained_from``), up to where the weights started from: the
    records hold that path as it was on the training machine. The records name the ModelNet40 folder
    ``$MODELNET40``; the recipes give its place beside a clone."""
    from dit_jax.network import checkpoint
    from dit_jax.pipeline import registration

    extra, records = checkpoint.read_extra(registration.shipped_weights()), []
    while extra:
        records.append(extra.get("train_config"))
        extra = extra.get("trained_from")
    runs = sorted((ROOT / "configs" / "shipped").glob("run*.py"), key=lambda p: int(p.stem[3:]))
    assert len(records) == len(runs)  # run 0 (not kept) records nothing
    for path, record in zip(reversed(runs), records):
        recorded, recipe = training.TrainConfig.from_json(record), training.load_config(path)
        assert recorded.data_dir == "$MODELNET40" and recipe.data_dir.endswith("modelnet40_ply_hdf5_1024"), path
        recorded = dataclasses.replace(recorded, data_dir=recipe.data_dir)
        if not recipe.settings:  # one setting: how a mix would be thinned does not apply
            recipe = dataclasses.replace(recipe, mix_one_size=recorded.mix_one_size)
        assert dataclasses.replace(recorded, init_from=None) == dataclasses.replace(recipe, init_from=None), path
        assert recorded.init_from and recipe.init_from, path


def test_the_shipped_weights_record_holds_no_absolute_path_and_commands_that_run_today():
    """Every run in the shipped weights' record names its recipe file and today's command for it, which
    parses with train.py's flags and loads that recipe; no string in the record is an absolute path (the
    training machine's folders mean nothing on another)."""
    import shlex

    import train
    from dit_jax.network import checkpoint
    from dit_jax.pipeline import registration

    extra = checkpoint.read_extra(registration.shipped_weights())
    assert not [v for v in jax.tree.leaves(extra) if isinstance(v, str) and os.path.isabs(v)]
    files = [f for f in pathlib.Path(registration.shipped_weights()).rglob("*") if f.is_file()]
    assert not [f for f in files if b"/work/" in f.read_bytes() or b"/tmp/" in f.read_bytes()]
    runs = 0
    while extra:
        words = shlex.split(extra["command"])
        assert words[:3] == ["python", "train.py", "--config"] and words[3] == extra["recipe"], extra["command"]
        assert words[4] == "--workdir" and len(words) == 6, extra["command"]
        with pytest.MonkeyPatch.context() as patch:
            patch.chdir(ROOT)  # where the command is run
            _, config, workdir = train.parse(words[2:])
        assert config == training.load_config(ROOT / extra["recipe"]) and workdir == words[5]
        extra, runs = extra.get("trained_from"), runs + 1
    assert runs == len(list((ROOT / "configs" / "shipped").glob("run*.py")))


def test_ship_weights_exports_a_run_with_its_record(tmp_path, tiny_run):
    """tools/ship_weights.py on the tiny run: the checkpoint it writes restores, and its record names the
    command, the steps run and the last validation, with no absolute path in it."""
    import ship_weights

    from dit_jax.network import checkpoint

    out = tmp_path / "shipped"
    ship_weights.main(
        [str(tiny_run.workdir), "--command", "python train.py --config configs/tiny.py", "--out", str(out)]
    )
    params, config = checkpoint.restore(out)
    extra = checkpoint.read_extra(out)
    assert config == TINY.model_config() and extra["steps_run"] == 12 and extra["last_validation"]["step"] == 12
    assert extra["command"] == "python train.py --config configs/tiny.py"
    assert not [v for v in jax.tree.leaves(extra) if isinstance(v, str) and os.path.isabs(v)]
    assert not [f for f in out.rglob("*") if f.is_file() and str(tmp_path).encode() in f.read_bytes()]


def test_unseen_split_validates_on_held_out_training_categories(prepared):
    """With --unseen, validation pairs come from held-out shapes of categories 0-19 (never empty, never the
    test categories)."""
    config = dataclasses.replace(TINY, unseen=True)
    train_ds, val_ds = training.make_datasets(config, prepared)
    assert len(val_ds) > 0 and len(train_ds) > 0
    val_labels = val_ds.shapes.labels[val_ds.rows]
    assert np.all((val_labels >= 0) & (val_labels < 20))
    assert np.all(train_ds.shapes.labels[train_ds.rows] < 20)


def test_init_from_starts_at_a_model_checkpoint(tmp_path, prepared):
    from dit_jax.network import checkpoint, configs, model

    config = TINY
    source = tmp_path / "source"
    params = model.init(jax.random.PRNGKey(7), config.model_config())
    checkpoint.save(source, params, config.model_config())
    optimizer = training.make_optimizer(config, 10)
    state = training.loop._initialise_from(training.init_state(config, optimizer), str(source), optimizer)
    assert jax.tree.all(
        jax.tree.map(lambda a, b: bool(np.array_equal(np.asarray(a), np.asarray(b))), state.params, params)
    )
    wider = configs.tiny().replace(emb_dims=64, token_dim=8)
    # Only its shapes are read: zeros of the wider network's shapes, without compiling its initialisation.
    wider_shapes = jax.eval_shape(lambda: model.init(jax.random.PRNGKey(0), wider))
    checkpoint.save(tmp_path / "wider", jax.tree.map(lambda a: np.zeros(a.shape, a.dtype), wider_shapes), wider)
    with pytest.raises(ValueError, match="does not have this run's shape"):
        training.loop._initialise_from(training.init_state(config, optimizer), str(tmp_path / "wider"), optimizer)
    # A deeper run starts from the shallower checkpoint grown in depth. Whatever the deeper network's own
    # values (here random, in its shapes, without compiling its initialisation), its added layers' residual
    # outputs are zeroed, so it computes the shallow network's features: the same numbers, up to the float32
    # rounding of two differently compiled programs (bit-equal on the CPUs measured).
    grown = _grown_from(source, config, optimizer)
    points = jax.random.normal(jax.random.PRNGKey(1), (64, 3))
    moved = points @ jnp.asarray(random_rotation(np.random.default_rng(0)), jnp.float32).T
    deeper_model = grown_model_config(config.model)
    _, shallow_features = jax.jit(model.features, static_argnames="config")(params, points, moved, config.model)
    _, grown_features = jax.jit(model.features, static_argnames="config")(grown, points, moved, deeper_model)
    for name, shallow, deep in zip(shallow_features._fields, shallow_features, grown_features):
        np.testing.assert_allclose(np.asarray(deep), np.asarray(shallow), rtol=1e-6, atol=1e-6, err_msg=name)


def grown_model_config(model_config):
    return model_config.replace(n_blocks=model_config.n_blocks + 1)


def _grown_from(source, config, optimizer):
    """The params ``_initialise_from`` gives a run one PFT block deeper than the checkpoint at ``source``."""
    deeper = dataclasses.replace(config, model=grown_model_config(config.model))
    deeper_state = jax.eval_shape(lambda: training.init_state(deeper, optimizer))
    rng = np.random.default_rng(3)
    deeper_state = deeper_state.replace(
        params=jax.tree.map(lambda a: jnp.asarray(rng.normal(0.0, 0.3, a.shape), a.dtype), deeper_state.params)
    )
    return training.loop._initialise_from(deeper_state, str(source), optimizer).params


def test_a_network_grown_in_depth_registers_as_the_checkpoint_it_grew_from(shipped):
    """Every iteration's motion of the shipped network grown by one block equals the shipped network's.

    Trained weights on a pair they register: with untrained ones the scores are nearly flat, GMCCE keeps one
    or two matches, and the last bits of two compiled programs decide which (1.5 apart in rotation on one CPU,
    equal on another). Measured on the shipped weights over four pairs and XLA's AVX2 and AVX-512 code paths,
    each iteration's rotation and translation differ by at most 1e-6: the bound is ten times that.
    """
    from dit_jax.pipeline import registration

    params, shipped_config = shipped
    config = dataclasses.replace(TINY, model=shipped_config)
    grown = _grown_from(registration.shipped_weights(), config, training.make_optimizer(config, 10))
    src, tgt, turns = (jnp.asarray(a) for a in shared_point_pairs(1, n=128, m=128, batch=1))
    before = model.register(params, src, tgt, shipped_config)
    after = model.register(grown, src, tgt, grown_model_config(shipped_config))
    assert float(metrics.rotation_error_deg(before[0][0], turns[0])) < 0.1  # a pair the shipped network registers
    for key in ("step_rotation", "step_translation"):
        np.testing.assert_allclose(np.asarray(after[2][key]), np.asarray(before[2][key]), atol=1e-5, err_msg=key)


def test_training_curves_of_several_runs_plot_into_one_png(tmp_path):
    runs = {}
    for seed in (0, 1):
        workdir = tmp_path / f"seed{seed}"
        workdir.mkdir()
        lines = [{"step": s, "split": "train", "loss": 1.0 / s} for s in (5, 10, 15)]
        lines += [
            {
                "step": s,
                "split": "val",
                "rotation_error": 1e-4,
                "network_rotation_error": 20.0 / (1 + s),
                "network_match_accuracy": 0.5 + s / 40,
            }
            for s in (0, 10, 15)
        ]
        (workdir / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in lines[::-1]) + "\n")
        runs[f"seed {seed}"] = str(workdir)
    records = training.read_metrics(runs["seed 0"])
    assert [r["step"] for r in records["val"]] == [0, 10, 15] and [r["step"] for r in records["train"]] == [5, 10, 15]
    training.plot_curves(runs, str(tmp_path / "curves.png"), title="two seeds")
    assert (tmp_path / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def _last_params(workdir):
    import orbax.checkpoint as ocp

    manager = ocp.CheckpointManager(os.path.abspath(workdir / "checkpoints"), item_names=("state", "meta"))
    step = manager.latest_step()
    return step, manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore())).state["params"]


def _step_record(workdir, step):
    """The training line of ``step`` in a run's metrics.jsonl."""
    for line in (workdir / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if record["step"] == step and record["split"] == "train":
            return record
    raise AssertionError(f"no training line for step {step} in {workdir}")


def test_data_parallel_steps_equal_one_device_over_devices_and_processes(tmp_path, prepared, tiny_run):
    """Data parallelism changes no step: `train.py --distributed` in two local processes (localhost
    coordinator, gloo CPU collectives) with two CPU devices each, so the batch is split over devices within a
    process and across processes at once, trains the tiny preset for 12 steps into one workdir, and matches
    ``tiny_run`` (the same 12 steps on one device, in this process):

    * its first step's loss and gradient norm at float32 rounding (a gradient summed instead of averaged over
      devices, or a device's rows counted twice, shows here; Adam's update hides the gradient's scale);
    * its parameters after 12 steps at float tolerance.

    The two processes read the data ``tiny_run`` prepared (preparing at once is tested in test_data_shapes).
    """
    # One checkpoint and one validation, both at step 12: the same steps, less to save and wait for.
    args = [
        sys.executable,
        str(ROOT / "train.py"),
        *TINY_ARGS,
        "--config.ckpt_every=12",
        "--config.eval_every=12",
        "--no-progress",
        "--prepared-dir",
        prepared,
    ]
    # two CPU devices per process, whatever device count the environment asks for
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if "device_count" not in f)
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"{flags} --xla_force_host_platform_device_count=2")
    port = _free_port()
    procs = [
        subprocess.Popen(
            args
            + [
                "--workdir",
                str(tmp_path / "two"),
                "--distributed",
                "--coordinator",
                f"localhost:{port}",
                "--num-processes",
                "2",
                "--process-id",
                str(i),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=str(ROOT),
        )
        for i in range(2)
    ]
    outputs = [p.communicate(timeout=600) for p in procs]
    for p, (out, err) in zip(procs, outputs):
        assert p.returncode == 0, out[-1000:] + err[-3000:]
    results = [json.loads(out[out.index("{") :]) for out, _ in outputs]
    assert [(r["processes"], r["devices"]) for r in results] == [(2, 4), (2, 4)]
    assert results[0]["val"] == results[1]["val"]

    # The first step, four devices in two processes against one.
    one_workdir = tiny_run.workdir
    one, four = _step_record(one_workdir, 1), _step_record(tmp_path / "two", 1)
    summary = f"losses {one['loss']} {four['loss']}, grad norms {one['grad_norm']} {four['grad_norm']}"
    # The order of reductions differs across devices, and the gradient (through softmax at temperatures up
    # to 100 and the Procrustes derivative) magnifies float32 rounding to ~1e-5 relative.
    assert abs(one["loss"] - four["loss"]) < 1e-5 * abs(one["loss"]), summary
    assert abs(one["grad_norm"] - four["grad_norm"]) < 1e-3 * one["grad_norm"], summary

    # Twelve steps.
    (step_two, two), (step_one, reference) = _last_params(tmp_path / "two"), _last_params(one_workdir)
    assert step_two == step_one == 12
    import optax

    start = training.init_state(TINY_RECIPE, optax.sgd(0.1)).params
    moved = max(
        float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
        for a, b in zip(jax.tree.leaves(reference), jax.tree.leaves(start))
    )
    differ = max(
        float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
        for a, b in zip(jax.tree.leaves(reference), jax.tree.leaves(two))
    )
    leaves = [
        (np.asarray(a), np.asarray(b), np.asarray(c))
        for a, b, c in zip(jax.tree.leaves(reference), jax.tree.leaves(two), jax.tree.leaves(start))
    ]
    moved_norm = np.sqrt(sum(float(np.sum((a - c) ** 2)) for a, _, c in leaves))
    differ_norm = np.sqrt(sum(float(np.sum((a - b) ** 2)) for a, b, _ in leaves))
    assert moved > 1e-4  # it trained
    # Float rounding only: one device reduces the batch in another order than four, and Adam's normalisation
    # magnifies rounding in near-zero gradients over 12 steps, up to a step of the learning rate in a single
    # parameter, so the whole update is compared; other pairs, another order or other dropout masks move the
    # params by the order of the movement itself.
    assert differ_norm <= 1e-2 * moved_norm and differ <= 0.1 * moved, (differ_norm, moved_norm, differ, moved)
    # One log, written by process 0 alone: a line per step and per validation.
    records = [json.loads(line) for line in (tmp_path / "two" / "metrics.jsonl").read_text().splitlines()]
    assert sorted(r["step"] for r in records if r["split"] == "train") == list(range(1, 13))
    assert sorted(r["step"] for r in records if r["split"] == "val") == [12]


def test_the_batch_loss_is_the_mean_of_each_pairs_loss():
    """The batch runs as one part per device, each part's pairs one after another (on a CPU, each pair's
    gradients added up as it goes); its loss and gradients are the mean of each pair's on its own, with each
    pair's own dropout key."""
    config = dataclasses.replace(TINY_RECIPE, batch_size=4)
    model_config = config.model_config()
    params = training.init_state(config, training.make_optimizer(config, 1)).params
    rng = np.random.default_rng(5)
    src = rng.uniform(-1, 1, (4, config.n_points, 3)).astype(np.float32)
    rotation = np.stack([random_rotation(rng) for _ in range(4)]).astype(np.float32)
    batch = {
        "src": src,
        "tgt": np.einsum("bij,bnj->bni", rotation, src) + 0.1,
        "R": rotation,
        "t": np.full((4, 3), 0.1, np.float32),
    }
    key = jax.random.PRNGKey(9)

    def pair_loss(p, pair, pair_key):  # as a train step computes one pair's loss
        its = model.unroll(
            p,
            pair["src"],
            pair["tgt"],
            model_config,
            config.train_iters,
            differentiable=config.differentiable,
            dropout_key=pair_key,
        )
        return losses.dit_loss(
            its,
            pair["src"],
            pair["tgt"],
            pair["R"],
            pair["t"],
            match_radius=config.match_radius,
            correspondence_weight=config.correspondence_weight,
        )[0]

    single = jax.jit(jax.value_and_grad(pair_loss))
    singles = [
        single(params, {name: array[i] for name, array in batch.items()}, pair_key)
        for i, pair_key in enumerate(jax.random.split(key, 4))
    ]
    expected = float(np.mean([float(v) for v, _ in singles]))
    # Host arithmetic (NumPy): op-by-op JAX would compile each operation for each parameter's shape.
    mean_grads = jax.tree.map(lambda *g: np.mean([np.asarray(x) for x in g], axis=0), *[g for _, g in singles])
    scale = max(float(np.max(np.abs(g))) for g in jax.tree.leaves(mean_grads))
    # Two parts of two pairs (one device runs one part of four in every other test of this file).
    batched = jax.jit(lambda p, b: training.batch_loss_and_grads(p, b, model_config, config, key, 2))
    (value, _), grads = batched(params, batch)
    np.testing.assert_allclose(float(value), expected, rtol=1e-5)
    for got, want in zip(jax.tree.leaves(grads), jax.tree.leaves(mean_grads)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-4 * scale)


def test_bfloat16_training_gives_the_float32_loss_and_gradients_within_their_measured_spread(shipped):
    """``train_precision="bfloat16"`` rounds the network's product operands to bfloat16 in the train step.
    On pairs the shipped weights register (96 points, two pairs a batch, one registration iteration unrolled:
    half the compilation of two; seeds 1-6), its loss was within 0.08-0.60 % of float32's and its gradient
    within 1.6-4.2 % in norm (cosine 0.9991 or more); the bounds here are three to ten times those. The loss
    must differ at all: the setting reaches the step."""
    from conftest import shared_point_pairs

    params, model_config = shipped
    base = dataclasses.replace(training.TrainConfig(model=model_config), batch_size=2, train_iters=1)
    src, tgt, turns = shared_point_pairs(1, 96, 96, 2, turn_deg=30.0)
    batch = {"src": src, "tgt": tgt, "R": turns.astype(np.float32), "t": np.full((2, 3), 0.05, np.float32)}

    def loss_and_flat_grads(precision):
        config = dataclasses.replace(base, train_precision=precision)
        (loss, _), grads = jax.jit(
            lambda p, b: training.batch_loss_and_grads(p, b, config.train_model_config(), config, jax.random.PRNGKey(3))
        )(params, batch)
        return float(loss), np.concatenate([np.ravel(g) for g in jax.tree.leaves(grads)])

    loss32, grads32 = loss_and_flat_grads(None)
    loss16, grads16 = loss_and_flat_grads("bfloat16")
    assert 1e-5 < abs(loss16 - loss32) / loss32 < 2e-2
    assert np.linalg.norm(grads16 - grads32) / np.linalg.norm(grads32) < 0.2
    assert grads16 @ grads32 / np.linalg.norm(grads16) / np.linalg.norm(grads32) > 0.99


def test_the_train_precision_changes_the_step_only():
    config = dataclasses.replace(TINY_RECIPE, train_precision="bfloat16")
    assert config.train_model_config().precision == "bfloat16"
    assert config.model_config().precision == "highest"  # validation and the saved model
    assert training.TrainConfig.from_json(config.to_json()).train_precision == "bfloat16"
    with pytest.raises(ValueError, match="train_precision must be one of"):
        dataclasses.replace(TINY_RECIPE, train_precision="float16")


def test_max_angle_reaches_the_training_and_validation_pairs():
    config = dataclasses.replace(TINY_RECIPE, settings=(), max_angle=60.0)
    train_ds, val_ds = training.make_datasets(config, progress=False)
    for pairs in (train_ds.batch(np.arange(32)), val_ds.batch(np.arange(min(32, len(val_ds))))):
        largest = np.abs(pairs["euler_zyx"]).max()
        assert 45.0 < largest <= 60.0
    narrow, _ = training.make_datasets(dataclasses.replace(TINY_RECIPE, settings=()), progress=False)
    assert np.abs(narrow.batch(np.arange(32))["euler_zyx"]).max() <= 45.0
