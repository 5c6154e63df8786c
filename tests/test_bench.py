"""``osteonav bench`` (app/bench/bench.py): configuration files, jitter, caching, and a run end to end."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.bench import bench
from app.errors import ConfigError
from app.geometry import se3

TRIAL_SECONDS = 0.8


# --------------------------------------------------------------------------- configurations

def test_builtin_configurations_load_with_the_publications_settings():
    configs = {c.name: c for c in bench.resolve_configs(None)}
    assert list(configs)[:7] == list(bench.BUILTIN_ORDER)
    expected = {"A_cpu": (200, (80, 60), "joint"), "A_cadaver": (1500, (160, 120), "joint"),
                "thesis_blockwise": (600, (80, 60), "blockwise"), "thesis_joint": (1250, (80, 60), "joint")}
    for name, (n, res, sampling) in expected.items():
        c = configs[name]
        assert c.kind == "particle_filter"
        assert (c.tracker.particles, c.tracker.resolution, c.tracker.sampling) == (n, res, sampling)
    complex_ = configs["thesis_complex"].tracker.likelihood
    assert complex_.occlusion == "smooth_exponential" and complex_.classification and complex_.l0_weight > 0
    assert configs["icp"].kind == "icp" and configs["icp"].icp.resolution == (160, 120)


def test_particle_filter_configurations_are_plain_tracker_files():
    from app.config import load_config

    for name in ("A_cpu", "A_cadaver", "thesis_blockwise", "thesis_joint", "thesis_complex"):
        load_config(bench.BUILTIN_DIR / f"{name}.yaml")   # usable by `osteonav replay --config` as they are


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, key", [
    ("tracker: icp\nicp:\n  voxell: 0.002\n", "icp.voxell"),
    ("tracker: icp\nicp:\n  voxel: -1\n", "icp.voxel"),
    ("tracker: icp\nicp:\n  iterations: 2.5\n", "icp.iterations"),
    ("tracker: icp\nicp:\n  resolution: [160]\n", "icp.resolution"),
    ("tracker: icp\nicp:\n  ok_fitness: 1.5\n", "icp.ok_fitness"),
    ("tracker: icp\nfilter:\n  particles: 10\n", "filter"),
    ("tracker: kalman\n", "tracker"),
    ("tracker: particle_filter\nfilter:\n  particle: 10\n", "filter.particle"),
])
def test_bad_configuration_files_name_the_key(tmp_path, text, key):
    path = _write(tmp_path, "bad.yaml", text)
    with pytest.raises(ConfigError) as info:
        bench.load_bench_config(path)
    assert info.value.key == key
    assert str(path) in str(info.value)


def test_icp_file_with_some_keys_keeps_the_other_defaults(tmp_path):
    from app.baselines.icp import ICPParams

    config = bench.load_bench_config(_write(tmp_path, "fast_icp.yaml", "tracker: icp\nicp:\n  resolution: [80, 60]\n  iterations: 10\n"))
    assert config.name == "fast_icp"
    assert config.icp.resolution == (80, 60) and config.icp.iterations == 10
    assert config.icp.voxel == ICPParams().voxel


def test_unknown_configuration_name_lists_the_builtins():
    with pytest.raises(ConfigError, match="A_cpu") as info:
        bench.resolve_configs(["nonexistent"])
    assert info.value.key == "--configs"


# --------------------------------------------------------------------------- jitter

def test_jitter_is_the_rms_frame_to_frame_change_over_static_ground_truth():
    n = 10
    stamps = np.arange(n) * 0.1
    T_gt = np.repeat(np.eye(4)[None], n, axis=0)
    T_gt[7:, 0, 3] = 0.05                      # the bone moves between frames 6 and 7
    pairs = bench.static_pairs(T_gt, stamps, settle_s=0.25)
    assert pairs.tolist() == [False, False, False, True, True, True, True, False, True, True]
    # the estimate alternates +-1 mm in y and 0.5 deg about z: every static change is 2 mm and 1 deg
    T_est = np.repeat(np.eye(4)[None], n, axis=0)
    for k in range(n):
        sign = 1 if k % 2 else -1
        T_est[k] = se3.from_rotvec_trans(np.array([0, 0, np.deg2rad(0.5) * sign]), np.array([0, 1e-3 * sign, 0]))
    j = bench.jitter(T_est, pairs)
    assert j["pairs"] == 6
    assert j["translation_mm"] == pytest.approx(2.0)
    assert j["rotation_deg"] == pytest.approx(1.0)


def test_jitter_is_nan_without_static_frames():
    j = bench.jitter(np.repeat(np.eye(4)[None], 3, axis=0), np.zeros(3, dtype=bool))
    assert np.isnan(j["translation_mm"]) and j["pairs"] == 0


# --------------------------------------------------------------------------- end to end

@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    """A 0.8 s simulated static_clear trial (cached where standard_trials looks), then `osteonav bench`."""
    from app.cli import main
    from app.sim.simulator import DEFAULT_MESH, simulate

    root = tmp_path_factory.mktemp("bench")
    cache = root / "cache"
    trial = cache / DEFAULT_MESH.stem / "static_clear"
    simulate(trial, DEFAULT_MESH, "static_clear", seconds=TRIAL_SECONDS, seed=0)
    tiny = _write(root, "tiny.yaml", "filter:\n  particles: 40\nrender:\n  resolution: [40, 30]\n  mesh_triangles: 300\n")
    tiny_icp = _write(root, "tiny_icp.yaml", "tracker: icp\nicp:\n  resolution: [80, 60]\n  iterations: 10\n  model_samples: 1000\n")
    out_json, plots, runs = root / "bench.json", root / "plots", root / "runs"
    rc = main(["bench", "--trials", str(trial), "--configs", str(tiny), str(tiny_icp), "--quick",
               "--json", str(out_json), "--plots", str(plots), "--out", str(runs)])
    return {"rc": rc, "trial": trial, "cache": cache, "json": out_json, "plots": plots, "runs": runs}


def test_bench_writes_a_row_per_configuration_and_trial(bench_run, capsys):
    from app.outputs import unlisted

    assert bench_run["rc"] == 0
    assert unlisted(bench_run["runs"]) == [] and unlisted(bench_run["plots"]) == []   # --overwrite may clear them
    data = json.loads(bench_run["json"].read_text())
    rows = data["rows"]
    assert [(r["config"], r["trial"]) for r in rows] == [("tiny", "iliac_crest/static_clear"),
                                                         ("tiny_icp", "iliac_crest/static_clear")]
    assert {r["tracker"] for r in rows} == {"particle_filter", "icp"}
    for r in rows:
        n = r["frames"]
        # fps is the replay loop's own rate: it cannot be below frames over the whole run's wall time
        assert n > 60 and r["fps"] >= n / r["wall_s"] * (1 - 1e-9)
        assert len(r["series"]["add_mm"]) == n and len(r["series"]["status"]) == n
        for key in ("add_mm", "add_s_mm", "mdd_s_mm", "translation_mm", "rotation_deg", "vsd"):
            assert r[key]["median"] is not None, key
        assert r["add_s_mm"]["median"] <= r["add_mm"]["median"] + 1e-9
        assert 0.0 <= r["vsd_recall"] <= 1.0
        assert sum(r["status_pct"].values()) == pytest.approx(100.0)
        assert r["jitter"]["pairs"] > 15  # the bone is static: every pair after the 0.5 s settling time
        # dangerous frames are exactly the ok frames with ADD > 5 mm
        s = r["series"]
        assert r["dangerous_frames"] == sum(st == "ok" and a > 5.0 for st, a in zip(s["status"], s["add_mm"]))
        # the calibration is exact here: the camera-frame ADD is the base-frame ADD (up to the joints'
        # linear interpolation), and every ok frame's outline is scored (app/bench/template.py)
        t = r["template"]
        assert t["camera_truth"] == "camera_truth.txt"
        assert t["add_camera_mm"]["median"] == pytest.approx(r["add_mm"]["median"], abs=0.02)
        assert t["ok_frames_scored"] == s["status"].count("ok")
        if t["ok_frames_scored"]:
            assert 0.0 <= t["outline_mean_mm"]["median"] <= t["outline_max_mm"]
    # the ICP baseline starts 5 mm / 3 deg off and locks onto the clear static bone
    icp = rows[1]
    assert icp["add_mm"]["median"] < 3.0


def test_bench_errors_and_jitter_match_a_numpy_recomputation_from_the_files(bench_run):
    """ADD (mean model-point distance) and jitter (RMS frame-to-frame change over static pairs)
    recomputed in numpy from the run's estimate.txt, groundtruth.txt and the mesh. Tolerances: the
    TUM files round to 1 um and 1e-8 (quaternion), the series to 1e-4 mm: 0.01 mm is generous."""
    from app.trial.reader import open_trial
    from app.trial.tum import read_tum

    rows = json.loads(bench_run["json"].read_text())["rows"]
    reader = open_trial(bench_run["trial"])
    points = np.asarray(reader.load_mesh().vertices)
    for r in rows:
        stamps, T_est = read_tum(bench_run["runs"] / r["config"] / "iliac_crest" / "static_clear" / "estimate.txt")
        T_gt = np.asarray(reader.groundtruth[:len(stamps)])
        p_est = np.einsum("nij,mj->nmi", T_est[:, :3, :3], points) + T_est[:, None, :3, 3]
        p_gt = np.einsum("nij,mj->nmi", T_gt[:, :3, :3], points) + T_gt[:, None, :3, 3]
        add_mm = 1e3 * np.linalg.norm(p_est - p_gt, axis=2).mean(axis=1)
        np.testing.assert_allclose(r["series"]["add_mm"], add_mm, atol=0.01)
        static = np.r_[False, np.all(np.abs(np.diff(T_gt, axis=0)) < 1e-9, axis=(1, 2))] & \
            (stamps - stamps[0] >= bench.JITTER_SETTLE_S - 1e-5)   # TUM stamps round to 1 us
        dt = np.linalg.norm(np.diff(T_est[:, :3, 3], axis=0), axis=1)[static[1:]]
        assert r["jitter"]["pairs"] == int(static.sum())
        assert r["jitter"]["translation_mm"] == pytest.approx(1e3 * np.sqrt(np.mean(dt ** 2)), abs=0.01)


def test_bench_draws_error_and_rate_plots(bench_run):
    names = sorted(p.name for p in bench_run["plots"].glob("*.png"))
    assert names == ["error_iliac_crest__static_clear.png", "rate.png"]
    import cv2

    for p in bench_run["plots"].glob("*.png"):
        image = cv2.imread(str(p))
        assert image is not None and image.shape[0] >= 200 and image.shape[1] >= 300, p.name
        # a drawn plot, not a blank canvas: a sizeable share of pixels differs from the background
        background = np.median(image.reshape(-1, 3), axis=0)
        assert np.mean(np.any(np.abs(image.astype(int) - background) > 30, axis=2)) > 0.01, p.name


def test_standard_trials_reuse_the_cached_simulation(bench_run):
    from app.sim.simulator import DEFAULT_MESH

    stamp = (bench_run["trial"] / "frames.csv").stat().st_mtime_ns
    specs = bench.standard_trials(bench_run["cache"], ["static_clear"], seconds=TRIAL_SECONDS,
                                  meshes=[DEFAULT_MESH], progress=False)
    assert [(s.mesh, s.scenario) for s in specs] == [("iliac_crest", "static_clear")]
    assert specs[0].frames > 60
    assert (bench_run["trial"] / "frames.csv").stat().st_mtime_ns == stamp


def test_estimate_files_are_tum_files_evo_reads(bench_run):
    evo_ape = Path(sys.executable).parent / "evo_ape"
    if not evo_ape.exists() and shutil.which("evo_ape") is None:
        pytest.skip("evo is not installed (pip install evo)")
    exe = str(evo_ape) if evo_ape.exists() else shutil.which("evo_ape")
    for config in ("tiny", "tiny_icp"):
        estimate = bench_run["runs"] / config / "iliac_crest" / "static_clear" / "estimate.txt"
        proc = subprocess.run([exe, "tum", str(bench_run["trial"] / "groundtruth.txt"), str(estimate)],
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr + proc.stdout
        assert "rmse" in proc.stdout


def test_quick_bone_moves_trial_really_moves():
    """``bench --quick``'s bone_moves trial lasts until its move has ended: the ground truth that the
    simulator writes (world.bone_trajectory at the frame schedule) covers the whole 5 cm move
    (minimum jerk: the last frame, within 1/90 s of the end, is at > 99.9 % of it). The former
    quick length (1.5 s, the move's start) gave a static bone, byte-identical to static_clear."""
    from app.sim import world
    from app.sim.scenarios import get_scenario
    from app.sim.simulator import CLOCK_START, frame_schedule

    seconds = bench.quick_seconds()["bone_moves"]
    scenario = get_scenario("bone_moves", seconds)
    _, stamps = frame_schedule(scenario, np.random.default_rng(0))
    T = world.bone_trajectory(stamps - CLOCK_START, np.eye(4), scenario.bone_motion)
    moved = np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1)
    assert moved[-1] > 0.0499 and np.count_nonzero(moved > 1e-4) > 100   # > 1.1 s of frames off the start
    assert bench.quick_seconds()["static_clear"] == bench.QUICK_STATIC_S


def test_recorded_trials_cut_to_seconds_and_need_ground_truth(bench_run, tmp_path):
    from app.errors import TrialFormatError

    spec = bench.recorded_trials([bench_run["trial"]], seconds=0.3)[0]
    assert spec.scenario == "static_clear" and spec.max_frames == spec.frames and 20 <= spec.frames <= 28
    copy = tmp_path / "no_gt"
    shutil.copytree(bench_run["trial"], copy)
    (copy / "groundtruth.txt").unlink()
    with pytest.raises(TrialFormatError, match="ground truth"):
        bench.recorded_trials([copy])


# --------------------------------------------------------------------------- the issue-12 matrix: seeds, lengths, summary

def test_seconds_per_scenario_keep_the_plain_duration_for_the_others():
    from app.commands.bench import parse_seconds
    from app.sim.scenarios import SCENARIOS

    assert parse_seconds(None) is None
    assert parse_seconds(["2.5"]) == 2.5
    by_name = parse_seconds(["3", "bone_moves=4.5"])
    assert by_name["bone_moves"] == 4.5 and by_name["static_clear"] == 3.0 and set(by_name) == set(SCENARIOS)
    assert parse_seconds(["dropouts=4"])["static_occluded"] == SCENARIOS["static_occluded"].seconds
    for bad in (["-1"], ["bone_moves=0"], ["nosuch=3"], ["x"]):
        with pytest.raises(ConfigError, match="--seconds"):
            parse_seconds(bad)


def test_seeds_give_one_lazy_trial_per_seed_scenario_and_mesh(tmp_path):
    from app.sim.simulator import DEFAULT_MESH

    specs = bench.standard_trials(tmp_path, ["static_clear", "bone_moves"], seconds={"static_clear": 1.0, "bone_moves": 2.0},
                                  meshes=[DEFAULT_MESH], seeds=[0, 3], lazy=True)
    assert [(s.seed, s.scenario) for s in specs] == [(0, "static_clear"), (0, "bone_moves"), (3, "static_clear"),
                                                      (3, "bone_moves")]
    assert not any(tmp_path.iterdir())                       # nothing simulated yet
    assert specs[2].path == str(tmp_path / DEFAULT_MESH.stem / "static_clear_seed3") and specs[2].name.endswith("/seed3")
    assert specs[2].simulation["seed"] == 3 and specs[3].simulation["seconds"] == 2.0
    assert specs[1].frames == 180                            # estimated until simulated (90 Hz)


def test_after_rest_is_the_error_from_0_3_s_after_the_last_move():
    t = np.arange(0.0, 2.0, 0.1)
    T_gt = np.repeat(np.eye(4)[None], len(t), axis=0)
    T_gt[:, 0, 3] = np.minimum(t, 1.0) * 0.01                 # moves until t = 1.0, then rests
    add = np.where(t < 1.25, 5.0, 0.5)
    add[-1] = 0.9
    out = bench.after_rest(T_gt, t, add)
    assert out["rest_s"] == pytest.approx(1.0) and out["frames"] == int(np.sum(t >= 1.3 - 1e-9))
    assert out["max_add_mm"] == pytest.approx(0.9) and out["median_add_mm"] == pytest.approx(0.5)
    assert bench.after_rest(np.repeat(np.eye(4)[None], 5, axis=0), t[:5], add[:5]) is None   # never moves


def _moved_then_still(t, rest_at=1.0):
    T_gt = np.repeat(np.eye(4)[None], len(t), axis=0)
    T_gt[:, 0, 3] = np.minimum(t, rest_at) * 0.01             # moves until rest_at, then rests
    return T_gt


def test_refound_counts_from_the_bone_in_view_and_still_to_the_add_staying_under_2_mm():
    t = np.round(np.arange(0.0, 4.0, 0.1), 6)
    T_gt = _moved_then_still(t)
    in_view = np.where(t < 1.5, 0.0, 0.6)                      # out of view until 1.5 s after rest at 1.0 s
    add = np.where(t < 2.3, 60.0, 0.5)
    add[t == 2.0] = 1.0                                        # a dip under 2 mm that does not stay: not found yet
    out = bench.refound(T_gt, t, add, in_view)
    assert out["rest_s"] == pytest.approx(1.0) and out["visible_s"] == pytest.approx(1.5)
    assert out["refound_s"] == pytest.approx(0.8)              # 2.3 - 1.5
    add[-1] = 2.5                                              # off on the last frame: never found again
    assert bench.refound(T_gt, t, add, in_view)["refound_s"] is None
    assert bench.refound(T_gt, t, np.full(len(t), 0.3), in_view)["refound_s"] == 0.0   # never lost
    never_seen = bench.refound(T_gt, t, np.full(len(t), 0.3), np.zeros(len(t)))
    assert never_seen["visible_s"] is None and never_seen["refound_s"] is None
    assert bench.refound(np.repeat(np.eye(4)[None], len(t), axis=0), t, add, in_view) is None   # never moves


def test_in_view_share_is_the_share_of_points_projecting_into_the_image():
    from app.geometry.camera import PinholeCamera

    camera = PinholeCamera(np.array([[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]]), 100, 100)
    points = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])   # 2 of 4 in view at 0.5 m
    T_bone = np.eye(4)
    T_bone[2, 3] = 0.5
    T_camera = np.stack([np.eye(4), np.full((4, 4), np.nan)])  # the second frame has no camera pose
    share = bench.in_view_share(T_camera, np.stack([T_bone, T_bone]), points, camera)
    assert share.tolist() == [0.5, 0.0]


def _row(mesh, seed, add_med, ok, danger, rest=None):
    return {"config": "c", "scenario": "s", "mesh": mesh, "seed": seed, "add_mm": {"median": add_med, "p95": 2 * add_med},
            "rotation_deg": {"median": add_med / 2}, "lost_pct": 0.0, "status_pct": {"ok": ok},
            "dangerous_frames": danger, "after_rest": None if rest is None else {"max_add_mm": rest}}


def test_summary_gives_the_median_and_names_the_worst_run():
    rows = [_row("a", 0, 0.2, 90.0, 0), _row("b", 0, 0.9, 40.0, 3, rest=0.8), _row("a", 1, 0.4, 80.0, 0, rest=1.5)]
    (s,) = bench.summary(rows)
    assert s["runs"] == 3 and s["add_median"]["median"] == pytest.approx(0.4)
    assert s["add_median"]["worst"] == pytest.approx(0.9) and s["add_median"]["worst_run"] == "b#0"
    assert s["ok_pct"]["worst"] == pytest.approx(40.0) and s["ok_pct"]["worst_run"] == "b#0"   # least ok is worst
    assert s["dangerous_frames"] == 3 and s["dangerous_runs"] == ["b#0"]
    assert s["after_rest_max_add"]["worst"] == pytest.approx(1.5) and s["after_rest_max_add"]["worst_run"] == "a#1"
    text = bench.summary_table(rows, markdown=True)
    assert "0.40 / 0.90 (b#0)" in text and "3 (b#0)" in text


def test_summary_gives_refound_median_and_worst_with_never_as_worst():
    rows = [_row("a", 0, 0.2, 90.0, 0), _row("b", 0, 0.9, 40.0, 0), _row("c", 0, 0.4, 80.0, 0), _row("d", 0, 0.4, 80.0, 0)]
    rows[0]["refound"] = {"visible_s": 2.4, "refound_s": 0.5}
    rows[1]["refound"] = {"visible_s": 2.4, "refound_s": 1.5}
    rows[2]["refound"] = {"visible_s": None, "refound_s": None}   # never in view after rest
    (s,) = bench.summary(rows)
    assert s["refound_s"]["median"] == pytest.approx(1.0) and s["refound_s"]["worst_run"] == "b#0"
    assert s["refound_s"]["not_in_view"] == ["c#0"]
    assert "1.00 / 1.50 (b#0), not in view: 1" in bench.summary_table(rows, markdown=True)
    rows[3]["refound"] = {"visible_s": 2.4, "refound_s": None}    # in view, never found again: the worst
    (s,) = bench.summary(rows)
    assert s["refound_s"]["never"] == ["d#0"] and "never (d#0)" in bench.summary_table(rows)
