"""Plans on the bone: the demo shapes, YAML polylines, transplant meshes, and their errors; ray casting."""
from pathlib import Path

import numpy as np
import pytest
import trimesh

from app.errors import ConfigError, MeshError
from app.projector.geometry import closest_points_on_mesh, distance_to_segments, ray_mesh_first_hit
from app.projector.plan import (Plan, load_plan, make_crest_plan, read_polyline_yaml, snap_to_surface,
                                write_polyline_yaml)

MESH = Path(__file__).resolve().parents[1] / "meshes" / "iliac_crest.ply"


@pytest.fixture(scope="module")
def bone():
    m = trimesh.load(MESH, process=False)
    return np.asarray(m.vertices, dtype=float), np.asarray(m.faces)


def test_ray_mesh_first_hit_matches_a_plane_in_closed_form():
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    rng = np.random.default_rng(0)
    origin = np.array([0.1, -0.2, 2.0])
    target = np.column_stack([rng.uniform(-1.5, 1.5, (200, 2)), np.zeros(200)])
    t, face = ray_mesh_first_hit(origin, target - origin, V, F)
    inside = np.all(np.abs(target[:, :2]) < 1, axis=1)
    np.testing.assert_allclose(t[inside], 1.0, atol=1e-12)
    assert np.all(np.isinf(t[~inside])) and np.all(face[~inside] == -1)


def test_ray_cone_prefilter_gives_the_brute_force_hits(bone):
    V, F = bone
    rng = np.random.default_rng(1)
    d = rng.normal(size=(300, 3)) * 0.05 + [0, 0, -1]
    o = np.array([0.01, 0.0, 0.3])
    t1, f1 = ray_mesh_first_hit(o, d, V, F)                      # one origin: pre-filtered
    t2, f2 = ray_mesh_first_hit(np.tile(o, (300, 1)), d, V, F)   # per-ray origins: brute force
    assert np.isfinite(t1).sum() > 100
    np.testing.assert_array_equal(f1, f2)
    np.testing.assert_allclose(t1, t2)


def test_distance_to_segments_by_hand():
    a, b = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])
    np.testing.assert_allclose(distance_to_segments([[0.5, 2, 0], [-3, 0, 4], [2, 0, 0]], a, b), [2, 5, 1])


@pytest.mark.parametrize("shape, size_mm", [("box", (20, 10)), ("hockey", (20, 26))])
def test_demo_shapes_lie_on_the_crest_and_close(bone, shape, size_mm):
    V, F = bone
    plan = make_crest_plan(shape, V, F, center_x=0.02 if shape == "hockey" else -0.02)
    line = plan.polylines[0]
    np.testing.assert_allclose(line[0], line[-1], atol=1e-9)
    _, dist, _ = closest_points_on_mesh(line, V, F)
    assert dist.max() < 5e-5        # 0.05 mm: the k-nearest-centroid search, not the plan
    extent = 1000 * (line[:, :2].max(axis=0) - line[:, :2].min(axis=0))
    np.testing.assert_allclose(extent, size_mm, atol=0.6)
    assert line[:, 2].max() > 0.0        # on the crest's top half (z up)


def test_unknown_shape_names_the_valid_ones(bone):
    with pytest.raises(ConfigError, match="box, hockey"):
        make_crest_plan("circle", *bone)


def test_yaml_plan_round_trip_in_millimetres(bone, tmp_path):
    V, F = bone
    plan = make_crest_plan("box", V, F, center_x=-0.02)
    path = tmp_path / "box.yaml"
    write_polyline_yaml(path, plan, units="mm")
    assert "units: mm" in path.read_text()
    loaded = load_plan(path, V, F)
    assert loaded.name == "box"
    assert distance_to_segments(loaded.points(), *plan.segments()).max() < 5e-5   # 0.1 um rounding, the nearest-point search


def test_plan_off_the_bone_is_a_mesh_error(bone, tmp_path):
    V, F = bone
    plan = make_crest_plan("box", V, F, center_x=-0.02)
    lifted = Plan(tuple(p + [0.0, 0.0, 0.005] for p in plan.polylines), "lifted")
    with pytest.raises(MeshError, match=r"not on the bone.*[45]\.\d mm from the bone surface"):
        snap_to_surface(lifted, V, F)
    path = tmp_path / "metres_as_mm.yaml"
    write_polyline_yaml(path, plan, units="m")
    path.write_text(path.read_text().replace("units: m", "units: mm"))   # the classic unit slip
    with pytest.raises(MeshError, match="units: mm"):
        load_plan(path, V, F)


@pytest.mark.parametrize("text, key", [
    ("name: x\n", "polylines"),
    ("units: inch\npolylines: [{points: [[0, 0, 0], [1, 0, 0]]}]\n", "units"),
    ("polylines: [{points: [[0, 0], [1, 0]]}]\n", r"polylines\[0\]\.points"),
    ("polylines: [[0, 0, 0]]\n", r"polylines\[0\]"),
])
def test_malformed_yaml_plan_names_the_key(tmp_path, text, key):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=key):
        read_polyline_yaml(path)


def test_unknown_plan_format_and_missing_file(bone, tmp_path):
    (tmp_path / "plan.txt").write_text("1 2 3")
    with pytest.raises(ConfigError, match="unknown plan format"):
        load_plan(tmp_path / "plan.txt", *bone)
    with pytest.raises(ConfigError, match="does not exist"):
        load_plan(tmp_path / "nothing.yaml", *bone)


def _transplant_prism(top: np.ndarray, depth: float) -> trimesh.Trimesh:
    """Open-topped prism under a closed ring on the bone: walls and a bottom, the top ring as boundary."""
    ring = top[:-1]
    n = len(ring)
    bottom = ring - [0.0, 0.0, depth]
    V = np.vstack([ring, bottom, bottom.mean(axis=0)])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i], [n + i, n + j, 2 * n]]
    return trimesh.Trimesh(V, np.array(faces), process=False)


def test_transplant_mesh_outline_is_its_rim_on_the_bone(bone, tmp_path):
    V, F = bone
    plan = make_crest_plan("box", V, F, center_x=-0.02, length=0.016, width=0.008, spacing=0.002)
    prism = _transplant_prism(plan.polylines[0], 0.012)
    path = tmp_path / "transplant.ply"
    prism.export(path)
    outline = load_plan(path, V, F)
    d = distance_to_segments(outline.points(), *plan.segments())
    assert d.max() < 1e-4                                    # only the rim, none of the bottom
    covered = distance_to_segments(plan.points(), *outline.segments())
    assert covered.max() < 1e-4                              # the whole rim
    far = prism.copy()
    far.apply_translation([0.0, 0.0, 0.05])
    far.export(tmp_path / "far.stl")
    with pytest.raises(MeshError, match="no edge of the transplant mesh lies on the bone"):
        load_plan(tmp_path / "far.stl", V, F)
