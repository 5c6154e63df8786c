"""Every malformed trial is rejected with a TrialFormatError that names the file and the line, key or frame."""
from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import yaml

from app.errors import TrialFormatError
from app.trial.reader import open_trial
from test_trial_io import HEIGHT, WIDTH, write_trial


@pytest.fixture
def trial(tmp_path, rng):
    out, written = write_trial(tmp_path, rng, n_frames=4)
    return out, written


def png_of(out, written, k: int):
    return out / "depth" / f"{written['frame_ids'][k]:06d}.png"


def edit_line(path, lineno: int, new: str | None) -> None:
    """Replace (or with None, delete) 1-based line ``lineno`` of a text file."""
    lines = path.read_text().splitlines()
    if new is None:
        del lines[lineno - 1]
    else:
        lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


def err(path, *parts: str) -> str:
    """A match= pattern: the file's path, then each part, in order."""
    return re.escape(str(path)) + ".*" + ".*".join(re.escape(p) for p in parts)


# ---------------------------------------------------------------- missing files

@pytest.mark.parametrize("name", ["trial.yaml", "frames.csv", "joints.csv"])
def test_missing_required_file(trial, name):
    out, _ = trial
    (out / name).unlink()
    with pytest.raises(TrialFormatError, match=err(out / name, "missing")):
        open_trial(out)


def test_missing_depth_png_names_file_and_frame(trial):
    out, w = trial
    png_of(out, w, 2).unlink()
    fid = w["frame_ids"][2]
    with pytest.raises(TrialFormatError, match=err(png_of(out, w, 2), f"(frame {fid})", "missing")):
        open_trial(out)


def test_missing_mesh_file(trial):
    out, _ = trial
    (out / "bone.ply").unlink()
    with pytest.raises(TrialFormatError, match=err(out / "trial.yaml", "key 'mesh'", "not found")):
        open_trial(out)


def test_not_a_directory(tmp_path):
    with pytest.raises(TrialFormatError, match="not a trial directory"):
        open_trial(tmp_path / "nowhere")


# ---------------------------------------------------------------- depth PNGs

def test_png_of_wrong_size(trial):
    out, w = trial
    cv2.imwrite(str(png_of(out, w, 1)), np.zeros((HEIGHT, WIDTH + 2), np.uint16))
    reader = open_trial(out)
    fid = w["frame_ids"][1]
    with pytest.raises(TrialFormatError, match=err(png_of(out, w, 1), f"(frame {fid})", "expected 32x24", "got 34x24")):
        list(reader.iter_frames())


def test_8_bit_png(trial):
    out, w = trial
    cv2.imwrite(str(png_of(out, w, 0)), np.zeros((HEIGHT, WIDTH), np.uint8))
    with pytest.raises(TrialFormatError, match=err(png_of(out, w, 0), "16-bit single-channel", "got uint8")):
        open_trial(out).read_depth(0)


def test_16_bit_colour_png(trial):
    out, w = trial
    cv2.imwrite(str(png_of(out, w, 0)), np.zeros((HEIGHT, WIDTH, 3), np.uint16))
    with pytest.raises(TrialFormatError, match=err(png_of(out, w, 0), "3 channel")):
        open_trial(out).read_depth(0)


def test_unreadable_png(trial):
    out, w = trial
    png_of(out, w, 3).write_bytes(b"not a png")
    with pytest.raises(TrialFormatError, match=err(png_of(out, w, 3), "cannot be read")):
        open_trial(out).read_depth(3)


# ---------------------------------------------------------------- frames.csv

FRAMES_CASES = [
    (3, "{id1},{s0}", "stamps must increase strictly"),            # equal stamp
    (3, "{id0},{s2}", "frame ids must increase strictly"),
    (4, "{id2},{s1}", "stamps must increase strictly"),
    (2, "x,{s0}", "frame must be an integer"),
    (2, "{id0},nan", "stamp must be finite"),
    (2, "{id0}", "expected 2 values"),
    (1, "frame,time", "expected the header 'frame,stamp'"),
]


def break_frames_csv(out, w, line: int, row: str) -> None:
    """Replace line ``line`` of frames.csv by ``row`` with {id0} {s0} ... filled from the trial."""
    ids, s = w["frame_ids"], w["stamps"]
    fields = {"id0": ids[0], "id1": ids[1], "id2": ids[2], "s0": f"{s[0]:.9f}", "s1": f"{s[1]:.9f}", "s2": f"{s[2]:.9f}"}
    edit_line(out / "frames.csv", line, row.format(**fields))


@pytest.mark.parametrize("line, row, message", FRAMES_CASES)
def test_bad_frames_csv_names_the_line(trial, line, row, message):
    out, w = trial
    break_frames_csv(out, w, line, row)
    with pytest.raises(TrialFormatError, match=err(out / "frames.csv", f"(line {line})", message)):
        open_trial(out)


def test_truncated_frames_row_without_interruption_marker_is_an_error(trial):
    out, _ = trial
    with open(out / "frames.csv", "a") as f:
        f.write("999,")
    with pytest.raises(TrialFormatError, match=err(out / "frames.csv", "(line 6)", "no line end")):
        open_trial(out)


@pytest.mark.parametrize("groundtruth", [True, False], ids=["with-groundtruth", "without-groundtruth"])
def test_frames_csv_cut_mid_line_names_frames_csv_and_the_line(trial, groundtruth):
    """A copy cut short inside a row (here in line 4's stamp) used to replay the first rows silently
    without groundtruth.txt, and to blame groundtruth.txt with it."""
    out, _ = trial
    if not groundtruth:
        (out / "groundtruth.txt").unlink()
    text = (out / "frames.csv").read_text()
    cut = text.index("\n", text.index("\n", text.index("\n") + 1) + 1) + 6   # 5 characters into line 4
    (out / "frames.csv").write_text(text[:cut])
    with pytest.raises(TrialFormatError, match=err(out / "frames.csv", "(line 4)", "no line end")):
        open_trial(out)


# ---------------------------------------------------------------- joints.csv

def test_nan_joint_value_names_the_line(trial):
    out, _ = trial
    edit_line(out / "joints.csv", 7, "12.000000,0.1,nan,0.3,0.4,0.5,0.6")
    with pytest.raises(TrialFormatError, match=err(out / "joints.csv", "(line 7)", "finite")):
        open_trial(out)


def test_missing_joint_column_in_header(trial):
    out, _ = trial
    edit_line(out / "joints.csv", 1, "stamp,q0,q1,q2,q3,q4")
    with pytest.raises(TrialFormatError, match=err(out / "joints.csv", "(line 1)", "stamp,q0,q1,q2,q3,q4,q5")):
        open_trial(out)


def test_missing_joint_value_in_a_row(trial):
    out, _ = trial
    row = (out / "joints.csv").read_text().splitlines()[4]
    edit_line(out / "joints.csv", 5, row.rsplit(",", 1)[0])
    with pytest.raises(TrialFormatError, match=err(out / "joints.csv", "(line 5)", "expected 7 values", "got 6")):
        open_trial(out)


def test_non_numeric_joint_value(trial):
    out, _ = trial
    edit_line(out / "joints.csv", 3, "12.0,0.1,zero,0.3,0.4,0.5,0.6")
    with pytest.raises(TrialFormatError, match=err(out / "joints.csv", "(line 3)", "'zero'")):
        open_trial(out)


def test_non_increasing_joint_stamps(trial):
    out, _ = trial
    lines = (out / "joints.csv").read_text().splitlines()
    edit_line(out / "joints.csv", 9, lines[6])   # line 9 repeats line 7's stamp
    with pytest.raises(TrialFormatError, match=err(out / "joints.csv", "(line 9)", "increase strictly")):
        open_trial(out)


# ---------------------------------------------------------------- groundtruth.txt

def test_groundtruth_stamp_mismatch_names_the_frame(trial):
    out, w = trial
    path = out / "groundtruth.txt"
    fields = path.read_text().splitlines()[3].split()   # pose 3 (line 4)
    fields[0] = f"{w['stamps'][2] + 1e-4:.9f}"
    edit_line(path, 4, " ".join(fields))
    with pytest.raises(TrialFormatError, match=err(path, f"(pose 3, frame {w['frame_ids'][2]})", "differs")):
        open_trial(out)


def test_groundtruth_with_a_missing_row(trial):
    out, _ = trial
    edit_line(out / "groundtruth.txt", 5, None)
    with pytest.raises(TrialFormatError, match=err(out / "groundtruth.txt", "3 poses for 4 frames")):
        open_trial(out)


def test_groundtruth_non_unit_quaternion(trial):
    out, _ = trial
    path = out / "groundtruth.txt"
    fields = path.read_text().splitlines()[1].split()
    fields[7] = "2.0"
    edit_line(path, 2, " ".join(fields))
    with pytest.raises(TrialFormatError, match=err(path, "(line 2)", "unit norm")):
        open_trial(out)


# ---------------------------------------------------------------- trial.yaml

def rewrite_yaml(out, change) -> None:
    path = out / "trial.yaml"
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def test_trial_yaml_not_yaml_names_the_line(trial):
    out, _ = trial
    path = out / "trial.yaml"
    path.write_text(path.read_text() + "camera: [unclosed\n")
    with pytest.raises(TrialFormatError, match=err(path, "(line ", "not valid YAML")):
        open_trial(out)


YAML_CASES = [
    ("format", lambda d: d.update(format="osteonav-trial/2"), "expected 'osteonav-trial/1'"),
    ("format", lambda d: d.pop("format"), "missing"),
    ("hand_eye", lambda d: d.pop("hand_eye"), "missing"),
    ("camera.K", lambda d: d["camera"].pop("K"), "missing"),
    ("camera.depth_scale", lambda d: d["camera"].pop("depth_scale"), "missing"),
    ("camera.width", lambda d: d["camera"].update(width=-640), "positive integer"),
    ("camera.K", lambda d: d["camera"].update(K=[[1.0, 0, 0], [0, 1, 0], [0, 0.5, 1]]), "last row must be [0, 0, 1]"),
    ("camera.K", lambda d: d["camera"].update(K=[[1.0, 0, 0], [0, 1, 0]]), "3x3 matrix"),
    ("camera.K", lambda d: d["camera"].update(K=[[float("nan"), 0, 0], [0, 1, 0], [0, 0, 1]]), "finite"),
    ("robot", lambda d: d["robot"].update(dh={"a": [0] * 6, "d": [0] * 6, "alpha": [0] * 6}), "got both"),
    ("robot", lambda d: d.update(robot={}), "got neither"),
    ("robot.model", lambda d: d.update(robot={"model": "ur7"}), "known models"),
    ("robot.dh", lambda d: d.update(robot={"dh": {"a": [0] * 6, "d": [0] * 6}}), "lacks alpha"),
    ("hand_eye", lambda d: d["hand_eye"][0].__setitem__(0, 2.0), "rigid 4x4"),
    ("initial_pose", lambda d: d.update(initial_pose=[[1, 0, 0, 0]]), "4x4 matrix"),
    ("point_prior", lambda d: d.update(point_prior=[1, "a", 2]), "expected a number, got 'a'"),
    ("mesh", lambda d: d.update(mesh=3), "expected a file name"),
]


@pytest.mark.parametrize("key, change, message", YAML_CASES)
def test_malformed_trial_yaml_names_the_key(trial, key, change, message):
    out, _ = trial
    rewrite_yaml(out, change)
    with pytest.raises(TrialFormatError, match=err(out / "trial.yaml", f"(key '{key}')", message)):
        open_trial(out)


def test_trial_yaml_that_is_not_a_mapping(trial):
    out, _ = trial
    (out / "trial.yaml").write_text("- just\n- a list\n")
    with pytest.raises(TrialFormatError, match=err(out / "trial.yaml", "expected a mapping")):
        open_trial(out)
