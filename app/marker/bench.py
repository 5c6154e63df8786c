"""Benchmark of publication C's tracking on the simulator: marker-only, IMU-only and fused.

Import as ``from app.marker import bench``; the command is ``osteonav bench-marker``.

Procedure (:func:`run`), all on :mod:`app.marker.simulator` sequences of one seed:

1. **Calibration**: a ``calibration`` sequence (the box turned by hand); markers detected in every
   image, the IMU slerped to the image stamps, X = R_S_M by Park & Martin
   (:mod:`app.marker.handeye_rotation`); its angle error against the truth is reported.
2. **Registration**: during the first ``registration_s`` of the ``pao`` sequence the box sits on
   the registration device; the APP is the average of orientations there (after 0.5 s): the
   marker's (camera frame) for marker-only; the IMU's (R_W_S X, its world) for IMU-only and for
   fused, as publication C records it. The fused tracker carries that plane into the camera frame
   with its IMU-to-camera alignment (:meth:`app.marker.fusion.MarkerImuFusion.plane_in_camera`),
   so its angles are of its fused R_C_M against ``R_C_P(t) = R_W_C(t)^T R_W_P``.
3. **Tracking** of the fragment; the acetabular axis in the marker frame is the plan's (exact in
   the simulation), so the errors are those of tracking, calibration and registration.
   - marker-only: every image searched whole, IPPE's lower-reprojection solution;
   - IMU-only: R_W_M = R_W_S X at every IMU sample;
   - fused: :class:`app.marker.fusion.MarkerImuFusion` (region first, Kalman filter).

Reported per method, over the fragment phase: mean absolute inclination and anteversion errors
(degrees) at the method's own updates, the same for the latest estimate held at every IMU stamp
(what a display refreshed at the IMU's rate shows: lag included), the update rate (outputs per
second of the sequence), and the host's compute time per update and its load (compute / sequence
time; below 1 keeps up in real time). For the fused tracker, which path found the marker.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from app.geometry import quaternion as quat
from app.marker import handeye_rotation as handeye
from app.marker import pelvic_plane as app_plane
from app.marker.aruco import MarkerDetector
from app.marker.fusion import MarkerImuFusion, slerp_at
from app.marker.kalman import OrientationKalman
from app.marker.simulator import MarkerScenario, MarkerSimulator

METHODS = ("marker", "imu", "fused")


def calibrate(scenario: MarkerScenario, seconds: float = 8.0) -> tuple[np.ndarray, dict]:
    """X = R_S_M (3, 3) from a simulated calibration sequence, and its report."""
    sim = MarkerSimulator(MarkerScenario(**{**scenario.__dict__, "motion": "calibration", "seconds": seconds,
                                            "seed": scenario.seed + 1000, "lighting": False}))
    det = MarkerDetector(sim.K, None, scenario.dictionary, scenario.marker_id, scenario.marker_length_m)
    rng = np.random.default_rng(scenario.seed + 2000)
    stamps, R_C_M = [], []
    for t in sim.frame_stamps():
        d = det.detect(sim.image(t, rng))
        if d.found:
            stamps.append(t)
            R_C_M.append(d.T_C_M[:3, :3])
    imu = sim.imu()
    R_W_S = quat.to_matrix(slerp_at(imu["stamp"], imu["q_W_S"], np.asarray(stamps)))
    X, report = handeye.calibrate_imu_to_marker(R_W_S, np.asarray(R_C_M), max_lag=5)
    err = np.rad2deg(np.linalg.norm(quat.log_map(quat.multiply(quat.conjugate(quat.from_matrix(X)),
                                                               quat.from_matrix(scenario.R_S_M)))))
    report.update(images=len(sim.frame_stamps()), detections=len(stamps), error_deg=float(err))
    return X, report


def _errors(sim: MarkerSimulator, stamps, R_ref_M, R_ref_P, t_from: float) -> dict:
    stamps = np.asarray(stamps, float)
    if len(stamps) == 0:
        return {"inclination_mae_deg": None, "anteversion_mae_deg": None, "n": 0}
    R_ref_M = np.asarray(R_ref_M)
    inc, ant = app_plane.fragment_angles(R_ref_P, R_ref_M, sim.axis_M)
    inc_t, ant_t = sim.angles(stamps)
    keep = stamps >= t_from
    return {"inclination_mae_deg": float(np.rad2deg(np.mean(np.abs(inc - inc_t)[keep]))),
            "anteversion_mae_deg": float(np.rad2deg(np.mean(np.abs(ant - ant_t)[keep]))), "n": int(keep.sum())}


def _held(stamps: np.ndarray, at: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The latest estimate at each time ``at`` (those before the first estimate are left out)."""
    idx = np.searchsorted(stamps, at, side="right") - 1
    ok = idx >= 0
    return at[ok], R[idx[ok]]


def run(seconds: float = 60.0, seed: int = 0, camera_fps: float = 10.0, imu_rate_hz: float = 100.0,
        progress=None, **scenario_overrides) -> dict:
    """Run the three methods on one simulated sequence; returns the results (see the module docstring)."""
    sc = MarkerScenario(seconds=seconds, seed=seed, camera_fps=camera_fps, imu_rate_hz=imu_rate_hz, **scenario_overrides)
    X, calib = calibrate(sc)
    if progress:
        progress(f"calibration: {calib['detections']}/{calib['images']} images, {calib['pairs']} pairs, "
                 f"error {calib['error_deg']:.2f} deg")
    sim = MarkerSimulator(sc)
    fusion = MarkerImuFusion(MarkerDetector(sim.K, None, sc.dictionary, sc.marker_id, sc.marker_length_m),
                             quat.from_matrix(X), OrientationKalman())
    played = _play(sc, sim, fusion, X, np.random.default_rng(seed + 3000), progress)
    results = {"scenario": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in sc.__dict__.items()},
               "calibration": calib, "render_s": played.render_s,
               "methods": {m: _method_result(sc, sim, played, m) for m in METHODS}}
    results["methods"]["marker"]["detected"] = f"{len(played.out['marker']['stamps'])}/{len(played.frames)}"
    results["methods"]["fused"]["paths"] = {k: fusion.counts[k] for k in ("roi", "full", "none")}
    results["methods"]["fused"]["gated"] = fusion.counts["gated"]
    results["methods"]["fused"]["kalman_resets"] = fusion.kalman.resets
    return results


@dataclass
class _Played:
    """What :func:`_play` gathered: per method (METHODS) the output stamps, R (orientation: R_C_M for the
    marker, R_W_M for the IMU alone, R_P_M for the fused tracker) and compute seconds; the image and IMU
    stamps; the seconds spent rendering images (not a method's cost)."""

    out: dict
    frames: np.ndarray
    imu_stamps: np.ndarray
    render_s: float


def _play(sc: MarkerScenario, sim: MarkerSimulator, fusion: MarkerImuFusion, R_S_M: np.ndarray, rng,
          progress=None) -> _Played:
    """Feed the sequence to the three methods in time order: each IMU sample, after the images stamped
    before it (module docstring)."""
    imu = sim.imu()
    frames = sim.frame_stamps()
    marker_det = MarkerDetector(sim.K, None, sc.dictionary, sc.marker_id, sc.marker_length_m)
    out = {m: {"stamps": [], "R": [], "compute_s": 0.0} for m in METHODS}
    reg_imu: list[np.ndarray] = []   # R_W_M of the IMU on the registration device (the fused tracker's APP)
    R_W_P = None
    k_img = 0
    render_s = 0.0
    for i, t_imu in enumerate(imu["stamp"]):
        while k_img < len(frames) and frames[k_img] < t_imu:
            render_s += _on_image(sim, marker_det, fusion, frames[k_img], rng, out)
            k_img += 1
        t0 = time.perf_counter()
        R_W_M = quat.to_matrix(imu["q_W_S"][i]) @ R_S_M
        out["imu"]["compute_s"] += time.perf_counter() - t0
        out["imu"]["stamps"].append(t_imu)
        out["imu"]["R"].append(R_W_M)
        t0 = time.perf_counter()
        est = fusion.on_imu(t_imu, imu["q_W_S"][i])
        if 0.5 <= t_imu < sc.registration_s:
            reg_imu.append(fusion.imu_marker_orientation())
        elif R_W_P is None and t_imu >= sc.registration_s and reg_imu:
            R_W_P = app_plane.register_pelvic_plane(np.asarray(reg_imu))
        R_C_P = None if R_W_P is None else fusion.plane_in_camera(R_W_P)
        out["fused"]["compute_s"] += time.perf_counter() - t0
        if est.q_C_M is not None and R_C_P is not None:
            out["fused"]["stamps"].append(t_imu)
            out["fused"]["R"].append(R_C_P.T @ quat.to_matrix(est.q_C_M))   # R_P_M: the plane is per sample
        if progress and i % int(10 * sc.imu_rate_hz) == 0 and i:
            progress(f"t = {t_imu:.0f} s")
    return _Played(out, frames, imu["stamp"], render_s)


def _on_image(sim: MarkerSimulator, marker_det: MarkerDetector, fusion: MarkerImuFusion, t_f: float, rng,
              out: dict) -> float:
    """One camera image at ``t_f`` to the marker alone and to the fused tracker (its correction shows in
    the next IMU-rate output); returns the seconds spent rendering it."""
    t0 = time.perf_counter()
    gray = sim.image(t_f, rng)
    render_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    d = marker_det.detect(gray)
    out["marker"]["compute_s"] += time.perf_counter() - t0
    if d.found:
        out["marker"]["stamps"].append(t_f)
        out["marker"]["R"].append(d.T_C_M[:3, :3])
    t0 = time.perf_counter()
    fusion.on_image(gray, t_f)
    out["fused"]["compute_s"] += time.perf_counter() - t0
    return render_s


def _method_result(sc: MarkerScenario, sim: MarkerSimulator, played: _Played, m: str) -> dict:
    """One method's errors against the truth, its own and held at the IMU's rate, and its cost."""
    st = np.asarray(played.out[m]["stamps"])
    R = np.asarray(played.out[m]["R"])
    if m == "fused":
        R_ref_P = np.eye(3)   # its orientations are R_P_M already
    else:
        reg = (st >= 0.5) & (st < sc.registration_s)
        R_ref_P = app_plane.register_pelvic_plane(R[reg])
    t_from = sim.fragment_start
    own = _errors(sim, st, R, R_ref_P, t_from)
    at, Rh = _held(st, played.imu_stamps, R)
    held = _errors(sim, at, Rh, R_ref_P, t_from)
    compute_s = played.out[m]["compute_s"]
    return {**own,
            "held_inclination_mae_deg": held["inclination_mae_deg"],
            "held_anteversion_mae_deg": held["anteversion_mae_deg"],
            "rate_hz": int((st >= t_from).sum()) / (sc.seconds - t_from),
            "compute_ms_per_update": 1e3 * compute_s / max(len(st), 1),
            "host_load": compute_s / sc.seconds}


def table(results: dict) -> str:
    """A Markdown table of :func:`run`'s results."""
    lines = ["| method | inclination MAE (deg) | anteversion MAE (deg) | held incl. / antev. MAE (deg) | "
             "update rate (Hz) | compute per update (ms) | host load |",
             "|---|---|---|---|---|---|---|"]
    names = {"marker": "marker only", "imu": "IMU only", "fused": "fused (Kalman)"}
    for m in METHODS:
        r = results["methods"][m]
        lines.append(f"| {names[m]} | {r['inclination_mae_deg']:.2f} | {r['anteversion_mae_deg']:.2f} | "
                     f"{r['held_inclination_mae_deg']:.2f} / {r['held_anteversion_mae_deg']:.2f} | "
                     f"{r['rate_hz']:.1f} | {r['compute_ms_per_update']:.3f} | {r['host_load']:.3f} |")
    return "\n".join(lines)
