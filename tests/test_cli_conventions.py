"""The command line's conventions (issue 34, deliver 3 and 5): numeric options checked at parse time
with the range in the message (app/cli_types.py), one option name per meaning with the old
spellings as hidden deprecated aliases, defaults in every help text, ``-v`` anywhere.

The misuse rows (a bad value on a real command line) are in test_misuse_matrix.py."""
from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pytest
import trimesh

from app import cli_types, strict_json
from app.cli import _subparsers, build_parser, main
from app.errors import MeshError

PARSER = build_parser()
SUBPARSERS = {sp.prog.removeprefix("osteonav "): sp for sp in _subparsers(PARSER)}
NUMERIC_TYPES = {int, float}


def _options(sp: argparse.ArgumentParser, hidden: bool = False):
    for a in sp._actions:
        if a.option_strings and (hidden or a.help != argparse.SUPPRESS):
            yield a


def _parse_error(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        PARSER.parse_args(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


# ---------------------------------------------------------------- numeric options

def test_no_option_parses_numbers_unchecked():
    """Every numeric option goes through a checking type; only a screen index may be any integer."""
    unchecked = [(name, a.option_strings) for name, sp in SUBPARSERS.items() for a in _options(sp, hidden=True)
                 if a.type in NUMERIC_TYPES]
    assert unchecked == [("calibrate projector", ["--screen"])]


@pytest.mark.parametrize("text", ["nan", "inf", "-inf", "x"])
def test_every_checked_numeric_option_refuses_a_non_finite_value_naming_itself(text, capsys):
    checked = [(name, a) for name, sp in SUBPARSERS.items() for a in _options(sp)
               if getattr(a.type, "__module__", None) == "app.cli_types"]
    assert len(checked) >= 25
    for name, action in checked:
        with pytest.raises(argparse.ArgumentTypeError, match="expected .*got"):
            action.type(text)


@pytest.mark.parametrize("kind, text, fragment", [
    (cli_types.positive_seconds, "0", "seconds > 0"),
    (cli_types.positive_seconds, "-1", "seconds > 0"),
    (cli_types.positive_int, "0", ">= 1"),
    (cli_types.positive_int, "1.5", ">= 1"),
    (cli_types.seed, "-1", ">= 0"),
    (cli_types.finite_positive_float, "0", "> 0"),
    (cli_types.int_at_least(3, "a capture count"), "2", "a capture count >= 3"),
    (cli_types.seconds_over(5.0, "why"), "5", "seconds > 5 (why)"),
])
def test_a_value_out_of_range_names_the_range(kind, text, fragment):
    with pytest.raises(argparse.ArgumentTypeError) as exc:
        kind(text)
    assert fragment in str(exc.value) and repr(text) in str(exc.value)


@pytest.mark.parametrize("kind, text, value", [
    (cli_types.positive_seconds, "0.05", 0.05), (cli_types.positive_int, "7", 7), (cli_types.seed, "0", 0),
    (cli_types.finite_positive_float, "1e-3", 0.001), (cli_types.finite_float, "-2.5", -2.5),
])
def test_a_value_in_range_is_returned(kind, text, value):
    assert kind(text) == value


def test_the_error_names_the_option_and_the_command(capsys):
    line = _parse_error(["simulate", "--out", "x", "--seconds", "0"], capsys)
    assert line == "osteonav simulate: error: argument --seconds: expected seconds > 0 (a finite number), got '0'"


def test_main_returns_the_parser_s_exit_codes(capsys):
    """In-process callers get an exit code, never SystemExit: 2 for a refused option, 0 for --help."""
    assert main(["simulate", "--out", "x", "--seed", "-1"]) == 2
    assert main(["simulate", "--help"]) == 0


# ---------------------------------------------------------------- names, aliases, help

DEPRECATED = [  # (command, old argv, new argv, dest)
    ("track", ["--duration", "2.5"], ["--seconds", "2.5"], "seconds"),
    ("record", ["--duration", "2.5"], ["--seconds", "2.5"], "seconds"),
    ("calibrate simulate", ["--captures", "6"], ["--count", "6"], "count"),
    ("view", ["--save", "x.rrd"], ["--rrd", "x.rrd"], "rrd"),
]
REQUIRED = {"track": ["--config", "s.yaml"], "record": ["--config", "s.yaml", "--out", "o"],
            "calibrate simulate": ["--out", "o"], "view": ["trial"]}


@pytest.mark.parametrize("command, old, new, dest", DEPRECATED, ids=[d[0] + d[1][0] for d in DEPRECATED])
def test_an_old_spelling_still_works_with_one_warning_and_is_hidden(command, old, new, dest, capsys):
    head = command.split()
    via_old = PARSER.parse_args(head + REQUIRED[command] + old)
    warning = capsys.readouterr().err.strip().splitlines()
    assert getattr(via_old, dest) == getattr(PARSER.parse_args(head + REQUIRED[command] + new), dest)
    assert warning == [f"osteonav {command}: warning: {old[0]} is deprecated; use {new[0]}"]
    assert old[0] not in SUBPARSERS[command].format_help()
    assert capsys.readouterr().err == ""   # the new spelling warns of nothing


def test_an_old_spelling_is_checked_like_the_new_one(capsys):
    assert "--duration: expected seconds > 0" in _parse_error(["track", "--config", "s.yaml", "--duration", "0"], capsys)


def test_one_name_per_meaning():
    """--captures is a folder wherever it shows, durations are --seconds, rerun logs --rrd."""
    shown = {(name, o): a for name, sp in SUBPARSERS.items() for a in _options(sp) for o in a.option_strings}
    assert not [k for k in shown if k[1] in ("--duration", "--save", "--projector-out")]
    captures = [a for (name, o), a in shown.items() if o == "--captures"]
    assert len(captures) >= 2 and all(a.type is not None and a.type.__name__ == "Path" for a in captures)
    assert all(a.type is not float for (name, o), a in shown.items() if o == "--seconds")


def test_every_optional_value_states_its_default():
    missing = [(name, a.option_strings) for name, sp in SUBPARSERS.items() for a in _options(sp)
               if not a.required and a.nargs != 0 and "default" not in (a.help or "") and "required" not in (a.help or "")]
    assert missing == []


def test_bench_configs_help_lists_every_builtin_it_runs_by_default():
    from app.bench.configs import builtin_configs

    text = " ".join(SUBPARSERS["bench"].format_help().split())
    assert len(builtin_configs()) >= 7
    for name in builtin_configs():
        assert name in text


@pytest.mark.parametrize("argv", [["-v", "simulate", "--out", "x"], ["simulate", "--out", "x", "-v"],
                                  ["simulate", "-v", "--out", "x"], ["calibrate", "hand-eye", "--captures", "c", "-v"]])
def test_verbose_is_accepted_before_and_after_the_subcommand(argv):
    assert PARSER.parse_args(argv).verbose is True


def test_verbose_is_off_unless_given():
    assert PARSER.parse_args(["simulate", "--out", "x"]).verbose is False


def test_the_pyglet_error_names_only_options_that_exist(monkeypatch):
    import sys

    from app.errors import GLError
    from app.projector.output import _import_pyglet

    monkeypatch.setitem(sys.modules, "pyglet", None)   # an absent pyglet: import raises ImportError
    with pytest.raises(GLError) as exc:
        _import_pyglet()
    named = re.findall(r"--[a-z][a-z-]+", str(exc.value))
    known = {o for sp in SUBPARSERS.values() for a in _options(sp) for o in a.option_strings}
    assert named and set(named) <= known


# ---------------------------------------------------------------- meshes and JSON

@pytest.mark.parametrize("extents, unit, scale", [((11.8, 3, 4), "centimetres", "0.01"),
                                                  ((120, 30, 40), "millimetres", "0.001")])
def test_the_unit_check_names_the_unit_that_makes_a_bone(tmp_path, extents, unit, scale):
    from app.mesh import check_units

    with pytest.raises(MeshError) as exc:
        check_units(trimesh.creation.box(extents=extents), "bone.ply")
    assert f"looks like {unit}" in str(exc.value) and str(exc.value).endswith(f"--scale {scale}")
    other = {"centimetres": "millimetres", "millimetres": "centimetres"}[unit]
    assert other not in str(exc.value)


def test_an_ambiguous_size_names_both_units_with_the_sizes_they_give():
    from app.mesh import check_units

    with pytest.raises(MeshError) as exc:
        check_units(trimesh.creation.box(extents=(30, 10, 10)), "bone.ply")
    assert "millimetres (3 cm across with --scale 0.001) or centimetres (30 cm across with --scale 0.01)" in str(exc.value)


def test_prepare_mesh_says_when_the_simplifier_stops_above_the_budget(tmp_path, monkeypatch, capsys):
    import fast_simplification

    def stuck(vertices, faces, **kwargs):   # a simplifier that cannot collapse anything (the 2 M -> 4,081 case)
        return vertices, faces

    monkeypatch.setattr(fast_simplification, "simplify", stuck)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.04)
    mesh.export(tmp_path / "sphere.ply")
    assert main(["prepare-mesh", str(tmp_path / "sphere.ply"), "--out", str(tmp_path / "out.ply"),
                 "--triangles", "100"]) == 0
    out = capsys.readouterr().out
    assert f"warning: the simplifier stopped at {len(mesh.faces)} triangles, above --triangles 100" in out


def test_strict_json_writes_null_for_non_finite_numbers():
    from dataclasses import asdict

    from app.bench.ambiguity import FrameDiagnosis

    row = FrameDiagnosis(3, 1.0, 0.9, 0.8, np.float32(0.5), 2.0, 3.0, float("nan"), float("nan"), np.inf, -np.inf)
    text = strict_json.dumps([asdict(row)], indent=1)
    loaded = json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in JSON"))
    assert loaded[0]["fit_best_refined"] is None and loaded[0]["refined_mm"] is None
    assert loaded[0]["ll_best"] == 0.5 and loaded[0]["frame"] == 3
    assert strict_json.finite_or_none({"a": np.array([1.0, np.nan])}) == {"a": [1.0, None]}


@pytest.mark.parametrize("seconds", [0, -1.0, float("nan"), float("inf")])
def test_simulate_refuses_a_duration_that_is_not_a_positive_number(tmp_path, seconds):
    """0 used to mean the scenario's 10 s; the function refuses it like the command line does."""
    from app.sim.simulator import simulate

    with pytest.raises(ValueError, match="seconds must be a finite duration > 0"):
        simulate(tmp_path / "t", scenario_name="static_clear", seconds=seconds)
    assert not (tmp_path / "t").exists()
