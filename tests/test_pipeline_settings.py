"""dit_jax.pipeline.settings: the pipeline's settings have one flag each, with the setting's choices, in every CLI."""

import argparse
import dataclasses

import calibrate
import pytest
import tune_baselines

import evaluate
import train
from dit_jax.cli import register, scene, series
from dit_jax.pipeline import settings

PARSERS = {
    "dit-register": register._parser,
    "dit-register-series": series._parser,
    "dit-register-scene": scene._parser,
    "evaluate.py": evaluate.build_parser,
    "tools/tune_baselines.py": tune_baselines.build_parser,
}
#: Programs that try several values of a setting (a grid) under the setting's own flag.
GRID_PARSERS = {"tools/calibrate.py": calibrate.build_parser}

#: Names a setting had before it had one: none of them may come back.
RETIRED = ("--n-points", "--no-verdict")

#: What each choice-taking field accepts, from the settings' own constants.
FIELD_CHOICES = {
    "refine": settings.REFINEMENTS,
    "feature_candidate": settings.FEATURE_CANDIDATES,
    "verdict_rule": settings.VERDICTS,
    "best_direction": settings.ON_OFF,
    "viewpoint": settings.VIEWPOINTS,
}


def _actions(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {option: action for action in parser._actions for option in action.option_strings}


def test_every_flag_names_fields_of_the_settings():
    fields = {field.name for field in dataclasses.fields(settings.InferenceSettings)}
    for flag in settings.FLAGS.values():
        assert set(flag.fields) <= fields, flag.name


@pytest.mark.parametrize("program", PARSERS)
def test_each_setting_has_one_flag_name_with_the_settings_choices_and_no_default(program):
    actions = _actions(PARSERS[program]())
    assert not set(RETIRED) & set(actions), program
    given = [flag for flag in settings.FLAGS.values() if flag.name in actions]
    assert given, f"{program} has none of the settings' flags"
    for flag in given:
        action = actions[flag.name]
        assert action.default is None, f"{program} {flag.name}: the default must be the checkpoint's"
        if len(flag.fields) == 1 and flag.fields[0] in FIELD_CHOICES:
            assert tuple(action.choices) == tuple(FIELD_CHOICES[flag.fields[0]]), f"{program} {flag.name}"
        assert "(default: the checkpoint's)" in action.help
    # No other option of the program sets one of these fields.
    names = {flag.dest for flag in settings.FLAGS.values()}
    other = [a.dest for a in actions.values() if a.dest not in names]
    for flag in settings.FLAGS.values():
        for field in flag.fields:
            assert field not in other, f"{program}: {field} has a second flag"


def test_the_same_flag_is_the_same_in_every_program():
    seen = {}
    for program, build in PARSERS.items():
        for option, action in _actions(build()).items():
            if option.lstrip("-").replace("-", "_") in settings.FLAGS:
                shape = (action.choices and tuple(action.choices), action.help, action.metavar, action.const)
                assert seen.setdefault(option, shape) == shape, f"{option} differs in {program}"
    assert set(seen) == {flag.name for flag in settings.FLAGS.values()}


@pytest.mark.parametrize("program", GRID_PARSERS)
def test_a_grid_of_a_setting_takes_the_settings_own_flag_and_values(program):
    actions = _actions(GRID_PARSERS[program]())
    given = [flag for flag in settings.FLAGS.values() if flag.name in actions]
    assert given, f"{program} has none of the settings' flags"
    for flag in given:
        action = actions[flag.name]
        assert action.nargs == "+" and action.default is None and action.type is flag.type, flag.name
        assert action.metavar == flag.metavar and action.help == f"values to try of: {flag.help}"
    assert not set(RETIRED) & set(actions)


def test_train_py_defines_no_flag_of_the_settings_under_another_meaning():
    """train.py's own flags and its ``--config.FIELD`` overrides name training's fields, none of the table's."""
    names = {name for name in train._define_flags()}
    assert not {flag.name.lstrip("-") for flag in settings.FLAGS.values()} & names


def test_parsed_flags_become_settings_changes_and_unset_ones_none():
    parser = register._parser()
    args = parser.parse_args(
        ["a", "b", "--points", "512", "--best-direction", "off", "--any-rotation", "--max-disagreement", "4.5"]
    )
    assert settings.changes(args) == {
        "n_points": 512,
        "best_direction": False,
        "rotation_search": True,
        "max_disagreement_network": 4.5,
        "max_disagreement_icp": 4.5,
    }
    assert settings.changes(parser.parse_args(["a", "b"])) == {}
    changed = settings.InferenceSettings().replace(**settings.changes(args))
    assert changed.n_points == 512 and changed.rotation_search and not changed.best_direction


def test_the_settings_module_imports_no_jax():
    import subprocess
    import sys

    code = "import sys, dit_jax.pipeline.settings; sys.exit('jax' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_the_descriptor_takes_a_name_or_a_weights_directory_and_refuses_anything_else(tmp_path):
    """``--descriptor`` has no fixed choices (a directory of one's own learned weights is a value); its metavar
    names the built-in ones, and the settings refuse what is neither in one line."""
    assert settings.FLAGS["descriptor"].metavar == "{" + ",".join(settings.DESCRIPTORS) + ",DIR}"
    for name in settings.DESCRIPTORS:
        assert settings.InferenceSettings(descriptor=name).descriptor == name
    with pytest.raises(ValueError, match="or a directory of learned descriptor weights, got .*nowhere"):
        settings.InferenceSettings(descriptor=str(tmp_path / "nowhere"))
