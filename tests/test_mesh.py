"""Bone meshes: loading, the millimetre check, tracking preparation, the prepare-mesh command and the default mesh."""
from __future__ import annotations

import itertools
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from app.cli import main as cli_main
from app.errors import MeshError
from app.mesh import check_units, load_mesh, outward_wound, prepare_mesh
from conftest import PELVIS_DIR, REPO, pelvis_meshes

DEFAULT_MESH = REPO / "meshes" / "iliac_crest.ply"
TRACKING_MESH = REPO / "meshes" / "iliac_crest_tracking.ply"


def test_default_mesh_is_an_asymmetric_crest_of_plausible_size():
    mesh = load_mesh(DEFAULT_MESH)
    check_units(mesh, DEFAULT_MESH)
    ext = mesh.extents
    assert 0.11 <= ext[0] <= 0.13 and 0.02 <= ext[1] <= 0.12 and 0.01 <= ext[2] <= 0.05
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)   # centred on its bounding box
    assert 3000 <= len(mesh.faces) <= 8000 and outward_wound(mesh)
    # no mirror symmetry about the centre planes and no half-turn symmetry about the axes: the
    # flipped vertices lie far from the surface (a box gives 0.3 mm here, the crest > 1 cm)
    surface = cKDTree(trimesh.sample.sample_surface(mesh, 40000, seed=1)[0])
    for signs in itertools.product((1.0, -1.0), repeat=3):
        if signs != (1.0, 1.0, 1.0):
            dist, _ = surface.query(np.asarray(mesh.vertices) * signs)
            assert np.mean(dist) > 5e-3, f"mesh looks symmetric under the axis flips {signs}"


def test_tracking_mesh_has_about_1000_triangles_and_matches_the_full_mesh():
    full, tracking = load_mesh(DEFAULT_MESH), load_mesh(TRACKING_MESH)
    assert 900 <= len(tracking.faces) <= 1000
    dist, _ = cKDTree(trimesh.sample.sample_surface(full, 40000, seed=1)[0]).query(tracking.vertices)
    assert np.max(dist) < 1.5e-3


def test_generator_reproduces_the_committed_meshes(tmp_path):
    subprocess.run([sys.executable, str(REPO / "meshes" / "make_default_mesh.py"), "--out", str(tmp_path)],
                   check=True, capture_output=True)
    for committed in (DEFAULT_MESH, TRACKING_MESH):
        new, old = load_mesh(tmp_path / committed.name), load_mesh(committed)
        np.testing.assert_array_equal(new.faces, old.faces)
        np.testing.assert_allclose(new.vertices, old.vertices, atol=1e-9)


def test_millimetre_mesh_is_rejected_with_the_fix(tmp_path):
    mm = load_mesh(DEFAULT_MESH)
    mm.apply_scale(1000.0)
    with pytest.raises(MeshError, match="looks like millimetres.*--scale 0.001"):
        check_units(mm, "bone_mm.ply")


def test_load_mesh_errors_name_the_file(tmp_path):
    with pytest.raises(MeshError, match="nowhere.ply: mesh file not found"):
        load_mesh(tmp_path / "nowhere.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(MeshError, match="bad.ply"):
        load_mesh(bad)


def test_scene_is_merged_into_one_mesh(tmp_path):
    scene = trimesh.Scene([trimesh.creation.box((0.01, 0.01, 0.01)),
                           trimesh.creation.box((0.01, 0.01, 0.01)).apply_translation([0.05, 0, 0])])
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh = load_mesh(path)
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) == 24


def test_prepare_mesh_centres_and_decimates(rng):
    mesh = load_mesh(DEFAULT_MESH)
    shift = rng.uniform(-0.1, 0.1, 3)
    mesh.apply_translation(shift)
    out = prepare_mesh(mesh, max_triangles=500)
    assert len(out.faces) <= 500 and len(out.faces) >= 400
    np.testing.assert_allclose(out.metadata["centering_offset"], shift, atol=1e-9)
    np.testing.assert_allclose(out.bounds.mean(axis=0), 0.0, atol=2e-3)
    assert outward_wound(out) and np.all(np.isfinite(out.vertices))
    kept = prepare_mesh(mesh, max_triangles=500, center=False)
    np.testing.assert_allclose(kept.metadata["centering_offset"], 0.0)


@pytest.mark.parametrize("pattern", ["crest_left_02.ply", "hip_right_03.ply"])
def test_prepare_mesh_command_on_pelvis_meshes(tmp_path, capsys, pattern):
    paths = pelvis_meshes(pattern)
    if not paths:
        pytest.skip(f"real pelvis meshes not found in {PELVIS_DIR} (the shared data folder is absent)")
    out = tmp_path / "tracking.ply"
    assert cli_main(["prepare-mesh", str(paths[0]), "--out", str(out), "--triangles", "800"]) == 0
    printed = capsys.readouterr().out
    assert "triangles" in printed and "centring offset" in printed and "extents" in printed
    mesh = load_mesh(out)
    assert 600 <= len(mesh.faces) <= 800
    np.testing.assert_allclose(mesh.extents, load_mesh(paths[0]).extents, rtol=0.05)


def test_prepare_mesh_command_scales_millimetres(tmp_path, capsys):
    mm = load_mesh(DEFAULT_MESH)
    mm.apply_scale(1000.0)
    mm.apply_translation([10.0, 20.0, 30.0])
    src = tmp_path / "bone_mm.stl"
    mm.export(src)
    assert cli_main(["prepare-mesh", str(src), "--out", str(tmp_path / "a.ply")]) == 2
    assert "--scale 0.001" in capsys.readouterr().err
    assert cli_main(["prepare-mesh", str(src), "--out", str(tmp_path / "b.ply"), "--scale", "0.001"]) == 0
    assert "centring offset: [0.010000, 0.020000, 0.030000] m" in capsys.readouterr().out
    np.testing.assert_allclose(load_mesh(tmp_path / "b.ply").extents, load_mesh(DEFAULT_MESH).extents, rtol=0.03)
