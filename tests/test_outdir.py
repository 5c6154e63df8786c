"""The overwrite policy (app/commands/outdir.py, app/outputs.py): a folder's manifest says what
osteonav wrote there; --overwrite removes exactly that, refuses anything else by name, and a second
writer is refused by the folder's lock."""
from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys

import pytest

from app import outputs
from app.commands.outdir import OutputError, prepare_dir, prepare_file
from app.outputs import LOCK, MANIFEST, close_all, read_manifest, wrote


@pytest.fixture(autouse=True)
def _release():
    yield
    close_all()


def _write(folder, *names):
    """Files written the way an osteonav writer does: listed first, then created."""
    for name in names:
        path = folder / name
        wrote(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("old")


def test_a_new_or_empty_directory_is_used_as_it_is(tmp_path):
    assert prepare_dir(tmp_path / "a" / "b", False).is_dir()
    (tmp_path / "empty").mkdir()
    assert prepare_dir(tmp_path / "empty", False) == tmp_path / "empty"


def test_a_non_empty_directory_needs_overwrite_and_then_loses_exactly_its_manifests_files(tmp_path):
    out = tmp_path / "out"
    prepare_dir(out, False)
    _write(out, "estimate.txt", "log.rrd", "projector/000001.png")
    close_all()
    assert read_manifest(out) == {"estimate.txt", "log.rrd", "projector/", "projector/000001.png"}
    with pytest.raises(OutputError, match=r"--out .*out is not empty \(3 entries of an earlier osteonav run, "
                                          r"e.g. estimate.txt\).*--overwrite"):
        prepare_dir(out, False)
    assert (out / "log.rrd").read_text() == "old"
    prepare_dir(out, True)
    assert sorted(p.name for p in out.iterdir()) == [LOCK, MANIFEST]
    close_all()
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST] and read_manifest(out) == set()


def test_overwrite_refuses_by_name_everything_the_command_did_not_write_and_removes_nothing(tmp_path):
    """The old rule owned `*.rrd`, `projector` and, beside a trial.yaml, everything."""
    out = tmp_path / "out"
    prepare_dir(out, False)
    _write(out, "trial.yaml", "log.rrd")
    close_all()
    (out / "thesis.tex").write_text("the user's")
    (out / "surgery_patient12.rrd").write_text("the user's")
    (out / "projector").mkdir()
    (out / "src").mkdir()
    (out / "src" / "main.c").write_text("the user's")
    with pytest.raises(OutputError, match=r"holds files this command did not write: projector/, src/, "
                                          r"surgery_patient12.rrd, thesis.tex;"):
        prepare_dir(out, True)
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "log.rrd", "projector", "src", "surgery_patient12.rrd",
                                                     "thesis.tex", "trial.yaml"]


def test_a_folder_without_a_manifest_is_never_cleared(tmp_path):
    """A trial.yaml (or a .recording-in-progress) no longer makes a folder osteonav's."""
    out = tmp_path / "trial"
    (out / "photos").mkdir(parents=True)
    for name in ("trial.yaml", ".recording-in-progress", "NOTES.txt"):
        (out / name).write_text("x")
    with pytest.raises(OutputError, match=r"did not write: \.recording-in-progress, NOTES.txt, photos/, trial.yaml"):
        prepare_dir(out, True)
    assert len(list(out.iterdir())) == 4


def test_a_file_in_a_folder_osteonav_created_is_still_refused(tmp_path):
    out = tmp_path / "out"
    prepare_dir(out, False)
    _write(out, "depth/000001.png")
    close_all()
    (out / "depth" / "mine.png").write_text("the user's")
    with pytest.raises(OutputError, match=r"did not write: depth/mine.png"):
        prepare_dir(out, True)
    assert (out / "depth" / "000001.png").exists()


def test_a_killed_run_lists_its_files_so_that_the_retry_can_overwrite_them(tmp_path):
    """A run killed after listing a file (and maybe before creating it) leaves a manifest the retry reads."""
    out = tmp_path / "out"
    code = (f"import os, sys; from app.outputs import open_folder, wrote; from pathlib import Path\n"
            f"out = Path({str(out)!r}); open_folder(out, False)\n"
            f"for name in ('trial.yaml', 'frames.csv', 'depth/000001.png', 'depth/000002.png.tmp'):\n"
            f"    wrote(out / name); (out / name).parent.mkdir(exist_ok=True); (out / name).write_text('x')\n"
            f"wrote(out / 'depth/000002.png')\n"
            f"os._exit(9)\n")
    assert subprocess.run([sys.executable, "-c", code], cwd=os.getcwd()).returncode == 9
    assert (out / LOCK).exists()          # left by the dead process: no longer held
    with pytest.raises(OutputError, match="is not empty .*earlier osteonav run.*--overwrite"):
        prepare_dir(out, False)
    prepare_dir(out, True)
    assert sorted(p.name for p in out.iterdir()) == [LOCK, MANIFEST]


def test_a_line_cut_by_a_kill_lists_nothing(tmp_path):
    (tmp_path / MANIFEST).write_text(json.dumps("a.txt") + "\n" + json.dumps("b.txt")[:3])
    assert read_manifest(tmp_path) == {"a.txt"}


def test_a_second_writer_is_refused_by_the_lock_and_a_dead_writers_lock_is_taken_over(tmp_path, caplog):
    out = tmp_path / "out"
    out.mkdir()
    held = os.open(out / LOCK, os.O_RDWR | os.O_CREAT)
    os.write(held, b"pid 999999, osteonav replay t --out out, since 2026-01-01 00:00:00\n")
    fcntl.flock(held, fcntl.LOCK_EX)
    try:
        with pytest.raises(OutputError, match=r"being written by another osteonav run \(pid 999999, osteonav replay"):
            prepare_dir(out, True)
    finally:
        os.close(held)              # the writer dies: its lock is gone, its lock file stays
    assert prepare_dir(out, False) == out
    assert "no longer running, is taken over" in caplog.text
    assert f"pid {os.getpid()}" in (out / LOCK).read_text()


def test_a_busy_nested_output_folder_is_not_cleared(tmp_path):
    out = tmp_path / "out"
    prepare_dir(out, False)
    prepare_dir(out / "trial", False, "record")
    _write(out / "trial", "frames.csv")
    _write(out, "estimate.txt")
    close_all()
    held = os.open(out / "trial" / LOCK, os.O_RDWR | os.O_CREAT)
    fcntl.flock(held, fcntl.LOCK_EX)
    try:
        with pytest.raises(OutputError, match="trial/ .*being written by another osteonav run"):
            prepare_dir(out, True)
        assert (out / "estimate.txt").exists()
    finally:
        os.close(held)
    prepare_dir(out, True)   # out's manifest lists trial/, trial's its own files
    assert sorted(p.name for p in out.iterdir()) == [LOCK, MANIFEST]


def test_the_input_is_never_an_output(tmp_path):
    trial = tmp_path / "trial"
    trial.mkdir()
    with pytest.raises(OutputError, match=r"--out .*trial would hold the input .*trial it reads"):
        prepare_dir(trial, True, inputs=[trial])
    with pytest.raises(OutputError, match="would hold the input"):
        prepare_dir(tmp_path, True, inputs=[trial])
    mesh = tmp_path / "bone.ply"
    mesh.write_text("x")
    with pytest.raises(OutputError, match=r"--out .*bone.ply is the input this command reads"):
        prepare_file(mesh, True, inputs=[mesh])


def test_a_file_written_into_an_output_folder_joins_its_manifest(tmp_path):
    """calibrate hand-eye's default --out is CAPTURES/hand_eye.yaml: a later `calibrate simulate
    --out CAPTURES --overwrite` may remove it."""
    captures = tmp_path / "captures"
    prepare_dir(captures, False)
    _write(captures, "captures.csv")
    close_all()
    prepare_file(captures / "hand_eye.yaml", False)
    assert read_manifest(captures) == {"captures.csv", "hand_eye.yaml"}


def test_files_and_unusable_paths_are_one_line_errors(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(OutputError, match="is a file, not a directory"):
        prepare_dir(afile, True)
    with pytest.raises(OutputError, match="cannot create the directory"):
        prepare_dir(afile / "sub", True)
    with pytest.raises(OutputError, match="already exists; pass --overwrite"):
        prepare_file(afile, False)
    assert prepare_file(afile, True) == afile and afile.read_text() == "x"   # replaced only by the writer
    with pytest.raises(OutputError, match="is a directory"):
        prepare_file(tmp_path, True)
    with pytest.raises(OutputError, match="cannot create the folder"):
        prepare_file(afile / "x.yaml", True)


def test_wrote_outside_every_open_folder_does_nothing(tmp_path):
    wrote(tmp_path / "x.txt")
    assert not (tmp_path / MANIFEST).exists() and outputs._open == {}
