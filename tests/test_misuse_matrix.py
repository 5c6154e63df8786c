"""Every misuse of the command line found by issue 15, and every broken trial of test_trial_errors.py.

Each row runs one ``osteonav`` command line in-process (``app.cli.main``: an unexpected exception
would escape it and fail the test, so "no traceback" is checked by construction, and the printed
text is searched for one too) and asserts the exit code, a one-line error naming what is wrong,
and that no file that existed before the call was changed or removed (the tree is hashed before
and after). A few rows also run as a real subprocess (test_subprocess_rows_print_no_traceback).
"""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from app.cli import main
from test_trial_errors import FRAMES_CASES, YAML_CASES, break_frames_csv, edit_line, png_of, rewrite_yaml
from test_trial_io import HEIGHT, WIDTH, write_trial

REPO = Path(__file__).resolve().parents[1]
SIM_SESSION = REPO / "configs" / "sessions" / "simulated.yaml"


def tree_hashes(*roots: Path) -> dict[str, str]:
    """Path -> sha1 of every file under ``roots`` (directories by their presence)."""
    out = {}
    for root in roots:
        for p in sorted(root.rglob("*")):
            out[str(p)] = hashlib.sha1(p.read_bytes()).hexdigest() if p.is_file() else "dir"
    return out


def run_cli(argv: list[str], roots: "Path | list[Path]", capsys) -> tuple[int, str]:
    """(exit code, stdout + stderr) of ``osteonav argv``; asserts nothing under ``roots`` changed."""
    root = roots if isinstance(roots, list) else [roots]
    before = tree_hashes(*root)
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    text = out.out + out.err
    after = tree_hashes(*root)
    changed = [k for k, h in before.items() if after.get(k) != h]
    assert not changed, f"files changed or removed: {changed[:5]}"
    assert "Traceback" not in text
    return code, text


def error_line(text: str, command: str) -> str:
    lines = [ln for ln in text.splitlines() if f"osteonav {command}: error:" in ln]
    assert len(lines) == 1, text[-2000:]
    return lines[0]


# ---------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def sim_trial(tmp_path_factory) -> Path:
    """A 0.1 s simulated trial on the default mesh (read-only for the tests: copy it to change it)."""
    out = tmp_path_factory.mktemp("matrix") / "trial"
    assert main(["simulate", "--out", str(out), "--seconds", "0.1", "--seed", "3"]) == 0
    return out


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> Path:
    """A hand-eye capture folder (6 captures), and beside it ``projector/``: 3 projector board poses."""
    out = tmp_path_factory.mktemp("matrix") / "captures"
    assert main(["calibrate", "simulate", "--out", str(out), "--count", "6", "--seed", "2"]) == 0
    assert main(["calibrate", "projector", "--simulate", "3", "--captures", str(out.parent / "projector")]) == 0
    return out


def mm_mesh(path: Path) -> Path:
    trimesh.creation.box(extents=(120.0, 30.0, 40.0)).export(path)
    return path


def cm_mesh(path: Path) -> Path:
    """An 11.8 cm bone in centimetres: as millimetres it would be an 11.8 mm one."""
    trimesh.creation.box(extents=(11.8, 3.0, 4.0)).export(path)
    return path


def flat_mesh(path: Path) -> Path:
    """A mesh of zero-area triangles only (collinear or repeated vertices), bone-sized."""
    v = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.02, 0.0]])
    trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 1, 2], [1, 2, 1], [3, 3, 0]]), process=False).export(path)
    return path


def copy_trial(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


# ---------------------------------------------------------------- the table of issue 15

def _nonempty(tmp: Path, name: str = "old") -> Path:
    d = tmp / name
    d.mkdir()
    (d / "summary.json").write_text("{}")
    (d / "log.rrd").write_bytes(b"RRF2 old")
    return d


def _file(tmp: Path, name: str = "afile") -> Path:
    p = tmp / name
    p.write_text("not a directory\n")
    return p


def _mm_trial(tmp: Path, trial: Path) -> Path:
    t = copy_trial(trial, tmp / "mm_trial")
    mesh_name = yaml.safe_load((t / "trial.yaml").read_text())["mesh"]
    mm_mesh(t / mesh_name)
    return t


def _flat_trial(tmp: Path, trial: Path) -> Path:
    t = copy_trial(trial, tmp / "flat_trial")
    flat_mesh(t / yaml.safe_load((t / "trial.yaml").read_text())["mesh"])
    return t


def _session(tmp: Path, text: str) -> Path:
    p = tmp / "session.yaml"
    p.write_text(text)
    return p


# (id, build(tmp, trial, captures) -> argv, command, exit code, fragments the error line must hold)
ROWS = [
    ("replay-out-not-empty", lambda t, tr, c: ["replay", tr, "--out", _nonempty(t)], "replay", 2, ["not empty", "--overwrite"]),
    ("replay-no-rrd-out-not-empty", lambda t, tr, c: ["replay", tr, "--out", _nonempty(t), "--no-rrd"], "replay", 2,
     ["--overwrite"]),
    ("replay-out-is-a-file", lambda t, tr, c: ["replay", tr, "--out", _file(t)], "replay", 2, ["is a file"]),
    ("replay-out-unwritable", lambda t, tr, c: ["replay", tr, "--out", _file(t) / "sub"], "replay", 2,
     ["cannot create"]),
    ("replay-out-is-the-trial", lambda t, tr, c: ["replay", copy_trial(tr, t / "tr"), "--out", t / "tr", "--overwrite"],
     "replay", 2, ["is never an output"]),
    ("replay-mm-mesh", lambda t, tr, c: ["replay", _mm_trial(t, tr), "--out", t / "r"], "replay", 2,
     ["looks like millimetres", "prepare-mesh", "--scale 0.001"]),
    ("simulate-out-not-empty", lambda t, tr, c: ["simulate", "--out", _nonempty(t), "--seconds", "0.05"], "simulate", 2,
     ["--overwrite"]),
    ("simulate-over-a-trial", lambda t, tr, c: ["simulate", "--out", copy_trial(tr, t / "tr"), "--seconds", "0.05"],
     "simulate", 2, ["--overwrite"]),
    ("simulate-out-is-a-file", lambda t, tr, c: ["simulate", "--out", _file(t), "--seconds", "0.05"], "simulate", 2,
     ["is a file"]),
    ("simulate-overwrite-foreign-dir", lambda t, tr, c: ["simulate", "--out", _nonempty(t), "--overwrite",
                                                         "--seconds", "0.05"], "simulate", 2, ["did not write"]),
    ("simulate-mm-mesh", lambda t, tr, c: ["simulate", "--out", t / "s", "--mesh", mm_mesh(t / "mm.ply"),
                                           "--seconds", "0.05"], "simulate", 2, ["looks like millimetres", "prepare-mesh"]),
    ("calibrate-simulate-not-empty", lambda t, tr, c: ["calibrate", "simulate", "--out", copy_trial(c, t / "c"),
                                                       "--count", "3"], "calibrate", 2, ["--overwrite"]),
    ("calibrate-capture-not-empty", lambda t, tr, c: ["calibrate", "capture", "--config",
                                                      _session(t, "camera: simulated\nrobot: simulated\n"),
                                                      "--out", copy_trial(c, t / "c"), "--count", "3"],
     "calibrate", 2, ["--overwrite"]),
    ("calibrate-intrinsics-out-exists", lambda t, tr, c: ["calibrate", "intrinsics", "--images", c / "images",
                                                          "--out", c / "camera.yaml"], "calibrate", 2,
     ["already exists", "--overwrite"]),
    ("calibrate-intrinsics-no-images", lambda t, tr, c: ["calibrate", "intrinsics", "--images", t / "nowhere"],
     "calibrate", 2, ["--images", "does not exist"]),
    ("calibrate-hand-eye-out-exists", lambda t, tr, c: ["calibrate", "hand-eye", "--captures", c,
                                                        "--out", c / "truth.yaml"], "calibrate", 2, ["already exists"]),
    ("calibrate-hand-eye-rrd-is-a-dir", lambda t, tr, c: ["calibrate", "hand-eye", "--captures", c, "--out",
                                                          t / "he.yaml", "--rrd", t], "calibrate", 2, ["is a directory"]),
    ("calibrate-projector-out-exists", lambda t, tr, c: ["calibrate", "projector", "--captures", c,
                                                         "--out", c / "camera.yaml"], "calibrate", 2, ["already exists"]),
    ("calibrate-projector-simulate-into-poses", lambda t, tr, c: ["calibrate", "projector", "--simulate", "3",
                                                                  "--captures", c.parent / "projector"], "calibrate", 2,
     ["--captures", "not empty", "--overwrite"]),
    ("view-rrd-exists", lambda t, tr, c: ["view", tr, "--rrd", _file(t, "x.rrd")], "view", 2, ["already exists"]),
    ("view-rrd-not-rrd", lambda t, tr, c: ["view", tr, "--rrd", t / "x.txt"], "view", 2, [".rrd"]),
    ("prepare-mesh-out-xyz", lambda t, tr, c: ["prepare-mesh", REPO / "meshes" / "iliac_crest.ply", "--out",
                                               t / "x.xyz"], "prepare-mesh", 2, [".xyz", ".ply"]),
    ("prepare-mesh-out-exists", lambda t, tr, c: ["prepare-mesh", REPO / "meshes" / "iliac_crest.ply", "--out",
                                                  _file(t, "x.ply")], "prepare-mesh", 2, ["already exists"]),
    ("prepare-mesh-out-unwritable", lambda t, tr, c: ["prepare-mesh", REPO / "meshes" / "iliac_crest.ply", "--out",
                                                      _file(t) / "x.ply"], "prepare-mesh", 2, ["cannot create"]),
    ("bench-plots-not-empty", lambda t, tr, c: ["bench", "--trials", tr, "--configs", "icp", "--plots", _nonempty(t),
                                                "--json", t / "b.json"], "bench", 2, ["--plots", "--overwrite"]),
    ("bench-out-is-a-file", lambda t, tr, c: ["bench", "--trials", tr, "--configs", "icp", "--out", _file(t),
                                              "--json", t / "b.json"], "bench", 2, ["--out", "is a file"]),
    ("bench-marker-short", lambda t, tr, c: ["bench-marker", "--seconds", "3", "--json", t / "m.json"], "bench-marker", 2,
     ["--seconds", "> 5"]),
    ("record-out-not-empty", lambda t, tr, c: ["record", "--config", SIM_SESSION, "--out", _nonempty(t)], "record", 2,
     ["--overwrite"]),
    ("track-out-not-empty", lambda t, tr, c: ["track", "--config", SIM_SESSION, "--out", _nonempty(t)], "track", 2,
     ["--overwrite"]),
    ("track-record-not-empty", lambda t, tr, c: ["track", "--config", SIM_SESSION, "--out", t / "o", "--record",
                                                 copy_trial(tr, t / "tr")], "track", 2, ["record", "--overwrite"]),
    ("session-unknown-key", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated}\n"
                                              "robot: {plugin: simulated}\nloops: {}\n")], "track", 2,
     ["session.yaml", "config key 'loops'"]),
    ("session-unknown-camera-param", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated, "
                                                       "param: {}}\nrobot: {plugin: simulated}\n")], "track", 2,
     ["session.yaml", "camera.param"]),
    # ---- issue 34: numeric options at parse time, the range in the message
    *[(f"simulate-seconds-{v}", (lambda v: lambda t, tr, c: ["simulate", "--out", t / "s", "--seconds", v])(v),
       "simulate", 2, ["--seconds", "> 0"]) for v in ("0", "-1", "nan", "inf")],
    ("simulate-seed-negative", lambda t, tr, c: ["simulate", "--out", t / "s", "--seed", "-1"], "simulate", 2,
     ["--seed", ">= 0"]),
    ("demo-unknown-scenario", lambda t, tr, c: ["demo", "--scenario", "nope", "--dir", t / "d"], "demo", 2,
     ["--scenario", "nope", "static_clear"]),
    # the old code ran track/record --duration 0 until Ctrl-C and stopped --duration -1 at once with exit 0
    *[(f"{cmd}-{opt.strip('-')}-{v}", (lambda cmd, opt, v: lambda t, tr, c: [
        cmd, "--config", SIM_SESSION, "--out", t / "o", opt, v])(cmd, opt, v), cmd, 2, [opt, "> 0"])
      for cmd in ("track", "record") for opt, v in (("--duration", "0"), ("--duration", "-1"), ("--seconds", "nan"))],
    ("prepare-mesh-scale-inf", lambda t, tr, c: ["prepare-mesh", REPO / "meshes" / "iliac_crest.ply", "--out",
                                                 t / "x.ply", "--scale", "inf"], "prepare-mesh", 2, ["--scale", "> 0"]),
    ("prepare-mesh-scale-0", lambda t, tr, c: ["prepare-mesh", REPO / "meshes" / "iliac_crest.ply", "--out",
                                               t / "x.ply", "--scale", "0"], "prepare-mesh", 2, ["--scale", "> 0"]),
    ("prepare-mesh-cm-mesh", lambda t, tr, c: ["prepare-mesh", cm_mesh(t / "cm.ply"), "--out", t / "x.ply"],
     "prepare-mesh", 2, ["looks like centimetres", "--scale 0.01", "11.8 cm"]),
    ("simulate-cm-mesh", lambda t, tr, c: ["simulate", "--out", t / "s", "--mesh", cm_mesh(t / "cm.ply"),
                                           "--seconds", "0.05"], "simulate", 2, ["looks like centimetres", "--scale 0.01"]),
    ("prepare-mesh-degenerate", lambda t, tr, c: ["prepare-mesh", flat_mesh(t / "flat.ply"), "--out", t / "x.ply"],
     "prepare-mesh", 2, ["degenerate", "zero area"]),
    ("simulate-degenerate-mesh", lambda t, tr, c: ["simulate", "--out", t / "s", "--mesh", flat_mesh(t / "flat.ply"),
                                                   "--seconds", "0.05"], "simulate", 2, ["degenerate"]),
    ("replay-degenerate-mesh", lambda t, tr, c: ["replay", _flat_trial(t, tr), "--out", t / "r"], "replay", 2,
     ["degenerate"]),
    ("bench-rate-frames-0", lambda t, tr, c: ["bench-rate", "--frames", "0", "--json", t / "r.json"], "bench-rate", 2,
     ["--frames", ">= 1"]),
    ("bench-seeds-negative", lambda t, tr, c: ["bench", "--seeds", "-1", "--json", t / "b.json"], "bench", 2,
     ["--seeds", ">= 0"]),
    ("bench-seconds-nan", lambda t, tr, c: ["bench", "--trials", tr, "--seconds", "nan", "--json", t / "b.json"],
     "bench", 2, ["--seconds", "> 0"]),
    ("bench-marker-seconds-nan", lambda t, tr, c: ["bench-marker", "--seconds", "nan", "--json", t / "m.json"],
     "bench-marker", 2, ["--seconds", "> 5"]),
    ("bench-marker-camera-fps-0", lambda t, tr, c: ["bench-marker", "--camera-fps", "0", "--json", t / "m.json"],
     "bench-marker", 2, ["--camera-fps", "> 0"]),
    ("calibrate-simulate-count-2", lambda t, tr, c: ["calibrate", "simulate", "--out", t / "c", "--count", "2"],
     "calibrate simulate", 2, ["--count", ">= 3"]),
    ("session-unknown-scenario", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated, "
                                                   "params: {scenario: nope}}\nrobot: {plugin: simulated}\n")],
     "track", 2, ["session.yaml", "camera.params.scenario", "static_clear"]),
    ("session-negative-seconds", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated}\n"
                                                   "robot: {plugin: simulated, params: {seconds: -3}}\n")],
     "track", 2, ["session.yaml", "robot.params.seconds", "> 0"]),
    ("session-negative-seed", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated, "
                                                "params: {seed: -1}}\nrobot: {plugin: simulated}\n")],
     "track", 2, ["session.yaml", "camera.params.seed", ">= 0"]),
    ("session-loop-duration-nan", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated}\n"
                                                    "robot: {plugin: simulated}\nloop: {duration_s: .nan}\n")],
     "track", 2, ["session.yaml", "loop.duration_s"]),
    ("session-unknown-loop-key", lambda t, tr, c: ["track", "--config", _session(t, "camera: {plugin: simulated}\n"
                                                   "robot: {plugin: simulated}\nloop: {speed: 2}\n")], "track", 2,
     ["session.yaml", "loop.speed"]),
]


@pytest.mark.parametrize("build, command, code, fragments", [pytest.param(*r[1:], id=r[0]) for r in ROWS])
def test_misuse_is_one_line_error_and_changes_nothing(tmp_path, sim_trial, captures, capsys, build, command, code,
                                                      fragments):
    argv = build(tmp_path, sim_trial, captures)
    capsys.readouterr()
    exit_code, text = run_cli(argv, [tmp_path, sim_trial, captures.parent], capsys)
    assert exit_code == code, text[-2000:]
    line = error_line(text, command)
    for fragment in fragments:
        assert fragment in line, (fragment, line)


# ---------------------------------------------------------------- the reader's broken trials, replayed

def _frames_case(line, row):
    return lambda out, w: break_frames_csv(out, w, line, row)


def _yaml_case(change):
    return lambda out, w: rewrite_yaml(out, change)


def _write_png(kind):
    import cv2

    images = {"size": np.zeros((HEIGHT, WIDTH + 2), np.uint16), "8bit": np.zeros((HEIGHT, WIDTH), np.uint8),
              "colour": np.zeros((HEIGHT, WIDTH, 3), np.uint16)}

    def mutate(out, w):
        if kind == "garbage":
            png_of(out, w, 0).write_bytes(b"not a png")
        else:
            cv2.imwrite(str(png_of(out, w, 0)), images[kind])
    return mutate


def _append(name, text):
    def mutate(out, w):
        with open(out / name, "a") as f:
            f.write(text)
    return mutate


def _groundtruth_row(k, change):
    def mutate(out, w):
        path = out / "groundtruth.txt"
        fields = path.read_text().splitlines()[k].split()
        change(fields, w)
        edit_line(path, k + 1, " ".join(fields))
    return mutate


BROKEN = (
    [(f"missing-{n}", (lambda n: lambda out, w: (out / n).unlink())(n), n) for n in
     ("trial.yaml", "frames.csv", "joints.csv")]
    + [("missing-png", lambda out, w: png_of(out, w, 2).unlink(), "depth/"),
       ("missing-mesh", lambda out, w: (out / "bone.ply").unlink(), "trial.yaml"),
       ("png-wrong-size", _write_png("size"), "depth/"), ("png-8-bit", _write_png("8bit"), "depth/"),
       ("png-colour", _write_png("colour"), "depth/"), ("png-garbage", _write_png("garbage"), "depth/"),
       ("frames-cut-mid-line", _append("frames.csv", "999,"), "frames.csv"),
       ("joints-nan", lambda out, w: edit_line(out / "joints.csv", 7, "12.0,0.1,nan,0.3,0.4,0.5,0.6"), "joints.csv"),
       ("joints-header", lambda out, w: edit_line(out / "joints.csv", 1, "stamp,q0,q1,q2,q3,q4"), "joints.csv"),
       ("joints-not-a-number", lambda out, w: edit_line(out / "joints.csv", 3, "12.0,0.1,zero,0.3,0.4,0.5,0.6"),
        "joints.csv"),
       ("groundtruth-missing-row", lambda out, w: edit_line(out / "groundtruth.txt", 5, None), "groundtruth.txt"),
       ("groundtruth-stamp", _groundtruth_row(3, lambda f, w: f.__setitem__(0, f"{w['stamps'][2] + 1e-4:.9f}")),
        "groundtruth.txt"),
       ("groundtruth-quaternion", _groundtruth_row(1, lambda f, w: f.__setitem__(7, "2.0")), "groundtruth.txt"),
       ("trial-yaml-not-yaml", _append("trial.yaml", "camera: [unclosed\n"), "trial.yaml"),
       ("trial-yaml-a-list", lambda out, w: (out / "trial.yaml").write_text("- just\n- a list\n"), "trial.yaml")]
    + [(f"frames-line{line}-{message.split()[0]}-{i}", _frames_case(line, row), "frames.csv")
       for i, (line, row, message) in enumerate(FRAMES_CASES)]
    + [(f"trial-yaml-{key}-{i}", _yaml_case(change), "trial.yaml") for i, (key, change, _) in enumerate(YAML_CASES)]
)


@pytest.mark.parametrize("mutate, names", [pytest.param(m, n, id=i) for i, m, n in BROKEN])
def test_replay_of_a_broken_trial_is_one_line_error_and_changes_nothing(tmp_path, capsys, mutate, names):
    out, written = write_trial(tmp_path, np.random.default_rng(12345), n_frames=4)
    mutate(out, written)
    code, text = run_cli(["replay", out, "--out", tmp_path / "replay", "--no-projector"], tmp_path, capsys)
    assert code == 2
    assert names in error_line(text, "replay")


def test_the_matrix_covers_every_broken_trial_of_the_reader_tests():
    """26 broken trials were listed by issue 15; test_trial_errors.py has grown beyond them."""
    assert len(BROKEN) >= 26


# ---------------------------------------------------------------- a real process, a real traceback check

@pytest.mark.parametrize("args", [
    ["prepare-mesh", "meshes/iliac_crest.ply", "--out", "{tmp}/x.xyz"],
    ["replay", "{tmp}", "--out", "{tmp}/r"],
    ["view", "{tmp}/nothing"],
    ["simulate", "--out", "{tmp}/s", "--seconds", "nan"],
    ["prepare-mesh", "meshes/iliac_crest.ply", "--out", "{tmp}/x.ply", "--scale", "inf"],
], ids=["prepare-mesh-xyz", "replay-not-a-trial", "view-not-a-trial", "simulate-seconds-nan", "prepare-mesh-scale-inf"])
def test_subprocess_rows_print_no_traceback(tmp_path, args):
    argv = [a.format(tmp=tmp_path) for a in args]
    before = tree_hashes(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "app.cli", *argv], capture_output=True, text=True, cwd=REPO,
                          timeout=300, env={**os.environ, "DISPLAY": ""})
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr + proc.stdout
    assert len([ln for ln in proc.stderr.splitlines() if ": error:" in ln]) == 1
    assert tree_hashes(tmp_path) == before
