"""The overwrite policy of app/commands/outdir.py on its own: refuse, clear what is owned, never more."""
from __future__ import annotations

import pytest

from app.commands.outdir import REPLAY, TRIAL, OutputError, prepare_dir, prepare_file


def test_a_new_or_empty_directory_is_used_as_it_is(tmp_path):
    assert prepare_dir(tmp_path / "a" / "b", False, REPLAY).is_dir()
    (tmp_path / "empty").mkdir()
    assert prepare_dir(tmp_path / "empty", False, REPLAY) == tmp_path / "empty"


def test_a_non_empty_directory_needs_overwrite_and_then_loses_only_the_owned_entries(tmp_path):
    out = tmp_path / "out"
    (out / "projector").mkdir(parents=True)
    for name in ("estimate.txt", "log.rrd", "projector/000001.png"):
        (out / name).write_text("old")
    with pytest.raises(OutputError, match=r"--out .*out is not empty \(3 entries, e.g. estimate.txt\).*--overwrite"):
        prepare_dir(out, False, REPLAY)
    assert (out / "log.rrd").read_text() == "old"
    prepare_dir(out, True, REPLAY)
    assert list(out.iterdir()) == []


def test_overwrite_never_removes_what_the_command_did_not_write(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "log.rrd").write_text("old")
    (out / "notes.txt").write_text("the surgeon's notes")
    with pytest.raises(OutputError, match="holds 'notes.txt', which this command did not write"):
        prepare_dir(out, True, REPLAY)
    assert sorted(p.name for p in out.iterdir()) == ["log.rrd", "notes.txt"]   # nothing removed, not even log.rrd


def test_a_trial_directory_is_the_trials_entirely_and_nothing_else_is(tmp_path):
    trial = tmp_path / "trial"
    (trial / "depth").mkdir(parents=True)
    for name in ("trial.yaml", "frames.csv", "bone.ply", "color.csv", "depth/000001.png"):
        (trial / name).write_text("x")
    prepare_dir(trial, True, TRIAL)
    assert list(trial.iterdir()) == []
    other = tmp_path / "other"
    other.mkdir()
    (other / "frames.csv").write_text("x")     # no trial.yaml: not a trial
    with pytest.raises(OutputError, match="did not write"):
        prepare_dir(other, True, TRIAL)


def test_files_and_unusable_paths_are_one_line_errors(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(OutputError, match="is a file, not a directory"):
        prepare_dir(afile, True, REPLAY)
    with pytest.raises(OutputError, match="cannot create the directory"):
        prepare_dir(afile / "sub", True, REPLAY)
    with pytest.raises(OutputError, match="already exists; pass --overwrite"):
        prepare_file(afile, False)
    assert prepare_file(afile, True) == afile and afile.read_text() == "x"   # replaced only by the writer
    with pytest.raises(OutputError, match="is a directory"):
        prepare_file(tmp_path, True)
    with pytest.raises(OutputError, match="cannot create the folder"):
        prepare_file(afile / "x.yaml", True)
