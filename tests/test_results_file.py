"""Benchmark results files follow the overwrite policy: an earlier run's JSON is never replaced silently."""
from __future__ import annotations

import pytest

from app.cli import main
from app.commands.outdir import OutputError, results_file


def test_an_explicit_results_file_that_exists_needs_overwrite(tmp_path):
    target = tmp_path / "r.json"
    target.write_text("earlier")
    with pytest.raises(OutputError, match="--overwrite"):
        results_file(str(target), "unused.json", overwrite=False)
    assert results_file(str(target), "unused.json", overwrite=True) == target
    assert target.read_text() == "earlier"       # resolving never writes


def test_the_default_results_file_gets_a_dated_name_when_it_exists(tmp_path):
    default = tmp_path / "sub" / "bench.json"
    assert results_file(None, str(default), overwrite=False) == default      # parent created
    default.write_text("earlier")
    other = results_file(None, str(default), overwrite=False)
    assert other.parent == default.parent and other.name.startswith("bench-") and other.suffix == ".json"
    assert other != default and default.read_text() == "earlier"
    assert results_file(None, str(default), overwrite=True) == default


@pytest.mark.parametrize("command", [["bench-rate", "--frames", "1"], ["bench-marker", "--seconds", "6"],
                                     ["bench", "--quick"]])
def test_benchmarks_refuse_to_replace_an_existing_json_before_any_work(tmp_path, capsys, command):
    target = tmp_path / "results.json"
    target.write_text("earlier")
    assert main([*command, "--json", str(target)]) == 2
    err = capsys.readouterr().err
    assert "--overwrite" in err and "Traceback" not in err
    assert target.read_text() == "earlier"
