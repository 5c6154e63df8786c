"""Every registered tracker plugin satisfies the typed contract of app/interfaces.py (``Tracker``,
returning a ``TrackerResult``) on frames of a simulated trial, through the per-frame core the live
loop and replay share; and the contract's ``result_scalars``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from app import plugins_registry as registry
from app.interfaces import STATUSES, DepthFrame, Tracker, TrackerResult, result_scalars
from app.pipeline.frame_core import FrameCore

FRAMES = 3


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    from app.sim.simulator import simulate
    from app.trial.reader import open_trial

    out = tmp_path_factory.mktemp("contract") / "trial"
    simulate(out, scenario_name="static_clear", seconds=0.2, seed=4)
    return open_trial(out)


PARAMS = {"marker_imu": {"imu": "simulated", "seed": 1}}


@pytest.mark.parametrize("name", registry.available("tracker"))
def test_every_registered_tracker_satisfies_the_contract(trial, name):
    tracker = registry.create("tracker", name, PARAMS.get(name, {}), "tracker", mesh=trial.load_mesh(),
                              camera=trial.meta.camera, T_flange_camera=trial.meta.T_flange_camera)
    assert isinstance(tracker, Tracker), f"{name} lacks a method or attribute of app.interfaces.Tracker"
    assert isinstance(tracker.description, str) and tracker.description
    tracker.start(trial.meta.initial_pose)
    core = FrameCore(tracker, [])
    T_base_camera, valid = trial.camera_poses()
    for i in range(FRAMES):
        frame = DepthFrame(int(trial.frame_ids[i]), float(trial.stamps[i]), trial.read_depth(i), float(trial.stamps[i]))
        est = core.process(frame, T_base_camera[i] if valid[i] else None)
        result = est.diagnostics["result"]
        assert isinstance(result, TrackerResult)
        assert np.shape(result.T_base_bone) == (4, 4) and np.all(np.isfinite(result.T_base_bone))
        assert result.status in STATUSES and est.status in STATUSES
        assert all(type(v) is float for v in result_scalars(result).values())
    positions = np.asarray(tracker.particle_positions())
    assert positions.ndim == 2 and positions.shape[1] == 3
    assert isinstance(tracker.mean_timings_ms(), dict)
    core.close()


def test_a_tracker_missing_a_method_fails_the_contract():
    class NoRelease:
        description = "x"

        def start(self, T): ...

        def process(self, frame, T_base_camera): ...

        def particle_positions(self): ...

        def mean_timings_ms(self): ...

    assert not isinstance(NoRelease(), Tracker)


def test_result_scalars_lists_the_numeric_fields_only():
    @dataclass
    class R:
        T_base_bone: np.ndarray
        status: str
        fitness: float
        count: int
        refined: bool
        timings: dict

    got = result_scalars(R(np.eye(4), "ok", 0.5, 3, True, {"a": 1.0}))
    assert got == {"fitness": 0.5, "count": 3.0, "refined": 1.0}
    assert result_scalars(object()) == {}
