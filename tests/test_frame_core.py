"""The per-frame core shared by replay and the live loop (app/pipeline/frame_core.py) and its sinks
(app/pipeline/sinks.py): the status floor, the estimate's diagnostics, the sinks' order, ground-truth
scoring against app/metrics.py, the TUM/status files against app/trial/tum.py, the rerun sink logging
every scalar of the tracker result, the projector every n-th estimate; and that replay through the
core gives the same trajectory as the tracker driven by hand."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from app import metrics
from app.geometry import se3
from app.filter.status import Reason
from app.interfaces import DepthFrame, Estimate
from app.pipeline.frame_core import FrameCore
from app.pipeline.sinks import EstimateFiles, GroundTruthScoring, ProjectorEstimates, RerunSink, Trajectory
from app.trial import tum


@dataclass
class Result:
    T_base_bone: np.ndarray
    status: str
    position_spread: float = 0.002
    rotation_spread: float = 0.01
    ess_ratio: float = 0.7
    covered_pixels: int = 120
    refined: bool = True
    template_std: float = 0.0004
    timings: dict = field(default_factory=dict)


class ScriptedTracker:
    """Returns the given statuses in turn, the pose moving 1 mm per frame along x."""

    description = "scripted"

    def __init__(self, statuses):
        self.statuses, self.n, self.released, self.seen = list(statuses), 0, False, []

    def start(self, T_base_bone):
        self.T = np.asarray(T_base_bone, float)

    def process(self, frame, T_base_camera):
        self.seen.append((frame.frame_id, T_base_camera is not None))
        T = self.T.copy()
        T[0, 3] += 1e-3 * self.n
        status = self.statuses[self.n % len(self.statuses)]
        self.n += 1
        return Result(T, status)

    def particle_positions(self):
        return np.zeros((5, 3))

    def mean_timings_ms(self):
        return {}

    def release(self):
        self.released = True


class Recorder:
    def __init__(self, name, order):
        self.name, self.order, self.estimates = name, order, []

    def on_estimate(self, est):
        self.order.append(self.name)
        self.estimates.append(est)

    def close(self):
        return {"seen": len(self.estimates)}


class FakeLog:
    """RerunLog's calls, recorded."""

    def __init__(self):
        self.scalars, self.bones, self.calls = {}, [], []

    def set_frame(self, frame_id, stamp):
        self.calls.append(("frame", frame_id))

    def log_camera(self, T_base_flange, T_base_camera, depth):
        self.calls.append(("camera", depth is not None))

    def log_images(self, infrared, color):
        self.calls.append(("images",))

    def log_bone(self, which, T):
        self.bones.append((which, T is not None))

    def log_particles(self, p):
        self.calls.append(("particles", len(p)))

    def log_scalar(self, name, value):
        self.scalars[name] = value

    def log_text(self, name, text):
        self.calls.append(("text", name, text))

    def close(self):
        pass


def frame(i, stamp=None):
    stamp = 0.1 * i if stamp is None else stamp
    return DepthFrame(i, stamp, np.full((4, 6), 0.5, np.float32), stamp)


def test_the_core_caps_the_status_fills_the_diagnostics_and_calls_sinks_in_order():
    tracker = ScriptedTracker(["ok"])
    tracker.start(np.eye(4))
    order = []
    a, b = Recorder("a", order), Recorder("b", order)
    clock = iter([10.0, 20.0])
    core = FrameCore(tracker, [a, b], now=lambda: next(clock))
    est = core.process(frame(0, stamp=9.5), np.eye(4), reasons=("r",))
    assert est.status == "ok" and est.latency_s == pytest.approx(0.5) and core.t_estimate == 10.0
    assert order == ["a", "b"] and a.estimates[0] is est and est.reasons == ("r",)
    d = est.diagnostics
    assert d["ess_ratio"] == 0.7 and d["position_spread"] == 0.002 and d["result"].covered_pixels == 120
    assert d["particles"].shape == (5, 3) and d["frame"].frame_id == 0 and d["T_base_bone_true"] is None
    assert core.process(frame(1), None, status_floor="uncertain").status == "uncertain"
    assert tracker.seen == [(0, True), (1, False)]
    reports = core.close()
    assert reports == {"Recorder": {"seen": 2}, "Recorder#2": {"seen": 2}} and tracker.released


def test_the_floor_never_improves_a_status_and_lost_wins():
    core = FrameCore(ScriptedTracker(["lost", "uncertain", "ok"]), [])
    core.tracker.start(np.eye(4))
    got = [core.process(frame(i), None, status_floor="uncertain").status for i in range(3)]
    assert got == ["lost", "uncertain", "uncertain"]
    assert core.process(frame(3), None, status_floor="lost").status == "lost"
    assert core.t_estimate is None, "no clock (replay): no latency"


def test_without_a_tracker_every_estimate_is_lost_not_tracking():
    rec = Recorder("r", [])
    core = FrameCore(None, [rec], now=lambda: 5.0)
    est = core.process(frame(0, stamp=4.0), np.eye(4))
    assert est.status == "lost" and est.T_base_bone is None and est.reasons == ("not tracking",)
    assert est.latency_s == 1.0 and core.t_estimate is None and rec.estimates == [est]


def test_a_failing_sink_does_not_stop_the_others_closing_or_the_tracker_release():
    class Broken(Recorder):
        def close(self):
            raise OSError("disk full")

    tracker = ScriptedTracker(["ok"])
    good = Recorder("good", [])
    reports = FrameCore(tracker, [good, Broken("x", [])]).close()
    assert reports["Broken"] == {"error": "disk full"} and reports["Recorder"] == {"seen": 0} and tracker.released


def test_ground_truth_scoring_matches_metrics_and_counts_lost_and_dangerous(rng):
    points = rng.normal(0, 0.02, (50, 3))
    scoring, traj = GroundTruthScoring(points), Trajectory()
    offsets_mm = [0.5, 6.0, 12.0, 6.0]
    statuses = ["ok", "ok", "uncertain", "uncertain"]
    for i, (off, status) in enumerate(zip(offsets_mm, statuses)):
        T_true = se3.from_rotvec_trans(rng.normal(0, 0.3, 3), rng.normal(0, 0.1, 3))
        T_est = T_true.copy()
        T_est[:3, 3] += [1e-3 * off, 0, 0]
        est = Estimate(0.1 * i, i, T_est, status, diagnostics={"T_base_bone_true": T_true})
        for sink in (scoring, traj):
            sink.on_estimate(est)
        assert est.diagnostics["errors"]["add_mm"] == pytest.approx(off, rel=1e-9)
        assert est.diagnostics["errors"]["add_mm"] == pytest.approx(1e3 * metrics.add(T_est, T_true, points))
    s = scoring.summary()
    assert s["add_mm"] == pytest.approx(metrics.summarise(np.array(offsets_mm)))
    assert s["lost_fraction"] == 0.25 and s["dangerous_frames"] == 1
    np.testing.assert_allclose(scoring.errors()["trans_mm"], offsets_mm)
    assert traj.statuses == statuses and len(traj.poses) == 4
    assert GroundTruthScoring(points).summary() == {}, "no truth, no error figures"


def test_estimate_files_write_the_rows_of_write_tum_and_write_status_csv(tmp_path, rng):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    stamps = np.cumsum(rng.uniform(0.01, 0.05, 6))
    poses = np.stack([se3.from_rotvec_trans(rng.normal(0, 1, 3), rng.normal(0, 1, 3)) for _ in stamps])
    statuses = ["ok", "uncertain", "lost", "ok", "ok", "lost"]
    reasons = {"uncertain": (Reason("behind", "slid?"), Reason("moving", "m"), Reason("behind", "again")),
               "lost": (Reason("no_pose", "no camera pose"),), "ok": ()}
    files = EstimateFiles(tmp_path / "a")
    for s, T, st in zip(stamps, poses, statuses):
        files.on_estimate(Estimate(s, 0, T, st, reasons=reasons[st], diagnostics={"state": "tracking"}))
    files.on_estimate(Estimate(stamps[-1] + 1, None, None, "lost"))   # a tick without a pose: a status row only
    files.close()
    tum.write_tum(tmp_path / "b" / "estimate.txt", stamps, poses)
    tum.write_status_csv(tmp_path / "b" / "status.csv", list(stamps) + [stamps[-1] + 1], statuses + ["lost"])
    assert (tmp_path / "a" / "estimate.txt").read_text() == (tmp_path / "b" / "estimate.txt").read_text()
    ours, plain = ((tmp_path / d / "status.csv").read_text().splitlines() for d in ("a", "b"))
    assert ours[0] == "stamp,status,state,reasons" and plain[0] == "stamp,status"
    assert [",".join(r.split(",")[:2]) for r in ours[1:]] == plain[1:]      # the format's two columns first
    assert ours[2].split(",")[2:] == ["tracking", "behind;moving"]          # the state, each code once
    assert ours[3].split(",")[2:] == ["tracking", "no_pose"] and ours[1].split(",")[2:] == ["tracking", ""]
    got_stamps, got = tum.read_status_csv(tmp_path / "a" / "status.csv")   # our reader reads both
    assert got == statuses + ["lost"] and np.allclose(got_stamps, list(stamps) + [stamps[-1] + 1], atol=1e-8)


def test_the_rerun_sink_logs_every_scalar_of_the_result_and_the_errors():
    log = FakeLog()
    sink = RerunSink(log, T_flange_camera=np.eye(4), depth_every=2, bone_when=("ok",))
    T = np.eye(4)
    for i, status in enumerate(["ok", "uncertain", "ok"]):
        result = Result(T, status)
        reasons = (Reason("behind", "1.2 % behind"),) if status != "ok" else ()
        sink.on_estimate(Estimate(0.1 * i, i, T, status, np.eye(4), 0.02, reasons,
                                  diagnostics={"frame": frame(i), "result": result, "particles": np.zeros((3, 3)),
                                               "T_base_bone_true": T, "errors": {"add_mm": 0.3},
                                               "state": "tracking" if status == "ok" else "suspect"}))
    texts = [c[1:] for c in log.calls if c[0] == "text"]
    assert texts[1] == ("status/reasons", "uncertain (suspect): behind: 1.2 % behind")   # why it is not ok, in the log
    assert texts[0] == ("status/reasons", "ok (tracking)")
    s = log.scalars
    assert s["spread/position_mm"] == pytest.approx(2.0) and s["spread/rotation_deg"] == pytest.approx(np.degrees(0.01))
    assert s["ess_ratio"] == 0.7 and s["tracker/covered_pixels"] == 120 and s["tracker/refined"] == 1.0
    assert s["refine/template_std_mm"] == pytest.approx(0.4) and s["tracker/reinitialised"] == 0.0
    assert s["error/add_mm"] == 0.3 and s["latency_ms"] == pytest.approx(20.0) and s["status"] == 0
    assert [b for b in log.bones if b[0] == "estimate"] == [("estimate", True), ("estimate", False), ("estimate", True)]
    assert ("groundtruth", True) in log.bones
    assert [c[1] for c in log.calls if c[0] == "camera"] == [True, False, True], "depth every 2nd estimate"


def test_the_rerun_sink_picks_up_a_new_result_field_such_as_reinitialised():
    @dataclass
    class Recovered(Result):
        reinitialised: bool = True

    log = FakeLog()
    RerunSink(log).on_estimate(Estimate(0.0, 0, np.eye(4), "ok", diagnostics={"result": Recovered(np.eye(4), "ok")}))
    assert log.scalars["tracker/reinitialised"] == 1.0


def test_the_projector_sink_renders_every_nth_estimate_with_the_truth():
    class FakeProjector:
        def __init__(self):
            self.steps, self.frames, self.released = [], 0, False

        def step(self, frame_id, T_base_camera, T_base_bone, status, age_s=0.0, T_base_bone_true=None):
            self.steps.append((frame_id, status, age_s, T_base_bone_true is not None))
            return "rendered"

        def summary(self):
            return {"frames": len(self.steps)}

        def release(self):
            self.released = True

    fake = FakeProjector()
    sink = ProjectorEstimates(fake, every=3, age_s=0.0)
    for i in range(7):
        sink.on_estimate(Estimate(0.1 * i, 10 + i, np.eye(4), "ok", latency_s=0.05,
                                  diagnostics={"T_base_bone_true": np.eye(4)}))
        assert (sink.last is not None) == (i % 3 == 0)
    assert fake.steps == [(10, "ok", 0.0, True), (13, "ok", 0.0, True), (16, "ok", 0.0, True)]
    assert sink.close() == {"frames": 3} and fake.released
    live = ProjectorEstimates(FakeProjector())
    live.on_estimate(Estimate(0.0, None, np.eye(4), "ok", latency_s=0.05))
    assert live.projector.steps == [(1, "ok", 0.05, False)], "live: the age is the latency; no frame id: the count"


def test_replay_through_the_core_equals_the_tracker_driven_by_hand(tmp_path):
    """Replay is deterministic and adds nothing to the tracker: its estimates, statuses and errors are
    those of a DepthTracker stepped frame by frame over the same trial (same config and seed)."""
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.pipeline.tracker import DepthTracker
    from app.sim.simulator import simulate
    from app.trial.reader import open_trial

    simulate(tmp_path / "trial", scenario_name="static_clear", seconds=0.15, seed=6)
    config = load_config(None)
    result = replay(tmp_path / "trial", tmp_path / "out", config, rrd=False, projector=False)
    reader = open_trial(tmp_path / "trial")
    tracker = DepthTracker(config, reader.load_mesh(), reader.meta.camera)
    tracker.start(reader.meta.initial_pose)
    T_base_camera, valid = reader.camera_poses()
    by_hand = [tracker.process(f.depth_m, f.stamp, T_base_camera[f.index] if valid[f.index] else None)
               for f in reader.iter_frames()]
    tracker.release()
    assert len(result.stamps) == len(by_hand) == len(reader) > 5
    np.testing.assert_array_equal(result.T_base_bone, np.array([r.T_base_bone for r in by_hand]))
    assert result.statuses == [str(r.status) for r in by_hand]
    points = np.asarray(reader.load_mesh().vertices)
    add = [1e3 * metrics.add(r.T_base_bone, reader.groundtruth[i], points) for i, r in enumerate(by_hand)]
    np.testing.assert_allclose(result.errors["add_mm"], add, rtol=1e-12)
    stamps, poses = tum.read_tum(tmp_path / "out" / "estimate.txt")
    np.testing.assert_allclose(poses, result.T_base_bone, atol=1e-8)
    assert result.summary["dangerous_frames"] == int(np.sum((np.array(add) > metrics.DANGEROUS_ADD_MM)
                                                            & (np.array(result.statuses) == "ok")))
