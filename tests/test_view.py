"""``osteonav simulate`` then ``osteonav view --rrd`` on the default mesh and on a real CT crest."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli import main
from tests.conftest import pelvis_meshes

MESHES = [None] + [pytest.param(p, id=p.name) for p in pelvis_meshes()[:1]]


def rerun_cli() -> Path:
    path = Path(shutil.which("rerun") or Path(sys.executable).parent / "rerun")
    if not path.exists():
        pytest.skip("rerun CLI not installed")
    return path


@pytest.mark.parametrize("mesh", MESHES)
def test_simulate_then_view_writes_a_recording_with_the_trial_entities(tmp_path, mesh):
    trial = tmp_path / "trial"
    args = ["simulate", "--out", str(trial), "--scenario", "static_occluded", "--seconds", "0.1", "--seed", "4"]
    if mesh is not None:
        args += ["--mesh", str(mesh)]
    assert main(args) == 0
    rrd = tmp_path / "trial.rrd"
    assert main(["view", str(trial), "--rrd", str(rrd)]) == 0
    assert rrd.read_bytes()[:4] == b"RRF2"
    text = subprocess.run([str(rerun_cli()), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120).stdout
    for entity in ("world/camera/image/depth", "world/bone/groundtruth", "world/robot/flange_path", "plots/occlusion"):
        assert entity in text, entity


def test_simulate_rejects_a_millimetre_mesh(tmp_path, capsys):
    import trimesh

    mesh = trimesh.creation.box(extents=(120.0, 30.0, 40.0))
    path = tmp_path / "mm.ply"
    mesh.export(path)
    assert main(["simulate", "--out", str(tmp_path / "t"), "--mesh", str(path), "--seconds", "0.05"]) == 2
    assert "--scale 0.001" in capsys.readouterr().err


def test_unknown_scenario_is_a_clear_error(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path / "t"), "--scenario", "nope"]) == 2
    assert "static_clear" in capsys.readouterr().err
