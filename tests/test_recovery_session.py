"""The recovery's inputs from the outside: ``bone.point_prior`` in the session file, the session's
start from it, and the plan's template points in the status bound (replay with a plan)."""
from __future__ import annotations

import numpy as np
import pytest

from app.errors import ConfigError
from app.pipeline.tracker import start_tracker, tracker_report
from app.session import parse_session


def _raw(**bone) -> dict:
    return {"camera": {"plugin": "simulated"}, "robot": {"plugin": "simulated"}, "bone": bone}


def test_point_prior_from_the_session_file(tmp_path):
    config = parse_session(_raw(point_prior=[0.61, -0.12, 0.05]), tmp_path)
    np.testing.assert_allclose(config.point_prior, [0.61, -0.12, 0.05])
    assert parse_session(_raw(), tmp_path).point_prior is None


@pytest.mark.parametrize("value", [[0.1, 0.2], "here", [0.1, "a", 0.2], [0.1, float("nan"), 0.2], [True, 0.0, 0.0]])
def test_a_bad_point_prior_is_named_with_the_fix(tmp_path, value):
    with pytest.raises(ConfigError, match=r"bone\.point_prior.*\[x, y, z\]"):
        parse_session(_raw(point_prior=value), tmp_path)


def test_resolve_session_passes_the_point_prior_on(tmp_path):
    from app.session.config import resolve_session

    config = parse_session(_raw(point_prior=[0.1, 0.2, 0.3]), tmp_path)
    ctx = resolve_session(config, None, {"robot": {"model": "ur5e"}, "T_flange_camera": np.eye(4)})
    np.testing.assert_allclose(ctx["point_prior"], [0.1, 0.2, 0.3])
    ctx = resolve_session(parse_session(_raw(), tmp_path), None,
                          {"robot": {"model": "ur5e"}, "T_flange_camera": np.eye(4), "point_prior": [1.0, 2.0, 3.0]})
    np.testing.assert_allclose(ctx["point_prior"], [1.0, 2.0, 3.0])


class _Inner:
    def __init__(self):
        self.calls = []

    def start(self, T):
        self.calls.append(("start", T.shape))

    def start_from_point(self, p):
        self.calls.append(("start_from_point", tuple(p)))

    def set_point_prior(self, p):
        self.calls.append(("set_point_prior", tuple(p)))

    def report(self):
        return {"recovery": {"reinitialisations": 0}}


def _Adapter():                       # a session plugin: the DepthTracker behind EngineTracker's .engine
    from app.pipeline.engine_tracker import EngineTracker

    return EngineTracker(_Inner())


def test_session_start_uses_the_pose_and_keeps_the_point_for_recovery():
    a = _Adapter()
    start_tracker(a, np.eye(4), np.array([1.0, 2.0, 3.0]))
    assert a.engine.calls == [("set_point_prior", (1.0, 2.0, 3.0)), ("start", (4, 4))]
    b = _Adapter()
    start_tracker(b, None, np.array([1.0, 2.0, 3.0]))     # no coarse start: the point starts the tracker
    assert b.engine.calls[-1] == ("start_from_point", (1.0, 2.0, 3.0))
    assert tracker_report(b) == {"recovery": {"reinitialisations": 0}}
    with pytest.raises(ConfigError, match="bone.initial_pose"):
        start_tracker(_Adapter(), None, None)
    assert tracker_report(None) == {}


def test_replay_with_a_plan_bounds_the_template_points(tmp_path):
    """The status's template error is over the plan's points (the summary says which) whether or not the
    projector is an output: the estimates never depend on the outputs (issue 34); the recovery's report
    is in the summary."""
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    simulate(tmp_path / "trial", scenario_name="static_clear", seconds=0.2, seed=2)
    with_plan = replay(tmp_path / "trial", tmp_path / "out", load_config(None), rrd=False)
    assert with_plan.summary["template_points"] == "plan"
    assert with_plan.summary["recovery"]["enabled"] and with_plan.summary["recovery"]["reinitialisations"] == 0
    without = replay(tmp_path / "trial", None, load_config(None), rrd=False, projector=False)
    assert without.summary["template_points"] == "plan"
    assert np.array_equal(without.T_base_bone, with_plan.T_base_bone) and without.statuses == with_plan.statuses


def test_plan_points_replace_the_vertices_in_the_bound(rng):
    """DepthTracker.use_plan_points: the refinement's bound is then over exactly those points."""
    import trimesh

    from app.config import load_config
    from app.filter.refine import template_std
    from app.geometry.camera import PinholeCamera
    from app.pipeline.tracker import DepthTracker

    mesh = trimesh.creation.box((0.08, 0.03, 0.02))
    camera = PinholeCamera(width=160, height=120, K=np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]]))
    tracker = DepthTracker(load_config(None), mesh, camera)
    plan = np.array([[0.0, 0.0, 0.01], [0.01, 0.0, 0.01]])
    tracker.use_plan_points(plan)
    track = tracker.refined_track
    np.testing.assert_allclose(track.plan_points + track.refiner.center, plan)
    H = np.diag([1e6, 1e6, 1e6, 1e3, 1e3, 1e3])
    # a far vertex is predicted worse than a point near the centre: the plan's bound is the smaller one
    vertices = np.asarray(mesh.vertices) - track.refiner.center
    assert template_std(H, track.plan_points, 1.0) < template_std(H, vertices, 1.0)
    assert tracker.report()["template_points"] == "plan"
    tracker.release()
