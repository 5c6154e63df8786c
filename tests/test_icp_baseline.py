"""The Open3D ICP baseline (app/baselines/icp.py) on a CT crest in soft tissue: with the model's
silhouette as its crop and the coarse-to-fine distances it stays on the bone from the start 5 mm off."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import PELVIS_DIR

CREST = PELVIS_DIR / "crest_right_02.ply"     # the crest the former crop lost first (82 mm after one frame)


@pytest.fixture(scope="module")
def crest_trial(tmp_path_factory):
    if not CREST.is_file():
        pytest.skip(f"{CREST} is not here (the shared CT crests)")
    from app.sim.simulator import simulate

    out = tmp_path_factory.mktemp("icp_crest") / "trial"
    simulate(out, mesh_path=CREST, scenario_name="static_clear", seconds=0.6, seed=0)
    return out


def _add_mm(T_a: np.ndarray, T_b: np.ndarray, vertices: np.ndarray) -> float:
    """ADD: the mean distance (mm) of the mesh's vertices between two poses."""
    a = vertices @ T_a[:3, :3].T + T_a[:3, 3]
    b = vertices @ T_b[:3, :3].T + T_b[:3, 3]
    return float(1e3 * np.linalg.norm(a - b, axis=1).mean())


def test_icp_stays_on_a_ct_crest_in_tissue(crest_trial):
    """Measured with the bench's settings (configs/bench/icp.yaml) on this trial (53 frames, the start
    5.2 mm off): ADD median 0.52 mm, max 1.68 mm, every frame ok. The former crop (2 cm around the bone,
    10 mm first distance) was 82 mm off after one frame of a 1.5 s trial of this crest and never came
    back. Bounds with a margin: the median under 1 mm, every frame under 3 mm, ok on 90 %."""
    from app.baselines.icp import ICPTracker
    from app.bench.configs import resolve_configs
    from app.trial.reader import open_trial

    reader = open_trial(crest_trial)
    mesh = reader.load_mesh()
    vertices = np.asarray(mesh.vertices)
    T_base_camera, valid = reader.camera_poses()
    icp = ICPTracker(resolve_configs(["icp"])[0].icp, mesh, reader.meta.camera)
    icp.start(reader.meta.initial_pose)
    assert _add_mm(reader.meta.initial_pose, reader.groundtruth[0], vertices) > 3.0     # a real start error
    add, statuses = [], []
    for i in range(len(reader)):
        result = icp.process(reader.read_depth(i), float(reader.stamps[i]), T_base_camera[i] if valid[i] else None)
        add.append(_add_mm(result.T_base_bone, reader.groundtruth[i], vertices))
        statuses.append(result.status)
    assert len(add) > 40
    assert np.median(add) < 1.0 and max(add) < 3.0
    assert statuses.count("ok") >= 0.9 * len(statuses)


def test_the_correspondence_distance_decreases_geometrically():
    from app.baselines.icp import ICPParams, ICPTracker

    tracker = ICPTracker.__new__(ICPTracker)
    tracker.params = ICPParams(max_distance_coarse=0.008, max_distance_fine=0.001, passes=4)
    np.testing.assert_allclose(tracker.distances(), [0.008, 0.004, 0.002, 0.001])
    tracker.params = ICPParams(passes=1)
    np.testing.assert_allclose(tracker.distances(), [ICPParams().max_distance_fine])
