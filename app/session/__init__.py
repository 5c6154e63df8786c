"""The intraoperative session: a session file, the plugins it names, and the live loop.

A session file (YAML, ``format: osteonav-session/1``; examples in ``configs/sessions/``)::

    camera:  {plugin: realsense, params: {width: 848, height: 480, fps: 30}}
    robot:   {plugin: ur, params: {host: 192.168.1.10}, model: ur5e}   # or dh: {a, d, alpha}
    tracker: {plugin: particle_filter, params: {config: ../default.yaml}}
    calibration:
      hand_eye: ../../calib/hand_eye.yaml     # 4x4 T_flange_camera (a file, or inline)
      intrinsics: null                        # optional; default: what the camera reports
    bone:
      mesh: ../../data/bone.ply               # the bone frame, metres
      initial_pose: ../../calib/initial_pose.yaml   # 4x4 T_base_bone (a file, or inline); or, instead,
      # point_prior: [0.61, -0.12, 0.05]      # a point on the bone, base frame, m (the detector starts there)
      # pointed_pixel: [424, 240]             # a depth pixel on the bone (column, row) of the first usable frame
      # pointer: {marker_id: 7, marker_length_m: 0.03, tip_offset_m: [0, -0.12, 0]}   # a tool's tip (ArUco)
    outputs: [{plugin: rerun, params: {path: session.rrd}}]
    record: recordings/today                  # optional: record the sensors as a trial
    out: recordings/today-tracking            # estimate.txt, status.csv, events.csv, summary.json
    loop: {stall_timeout_s: 0.5, duration_s: null}   # replay_rate: 0.25 plays a recorded source slower

Every relative path is relative to the session file, as ``config:`` is: inputs (calibration
files, ``bone.mesh``, plugin parameters named ``trial``, ``recording``, ``mesh``, ``config``) and
outputs alike (``out``, ``record``, an output plugin's ``path``/``dir``, a simulated trial's
``trial_dir``); the command line's ``--out``/``--record`` are relative to the current directory.
A recorded or simulated source
knows its trial's calibration, robot, mesh and initial pose; keys the file leaves out are taken
from there. Every error names the key (dotted) and the allowed values.

Modules: :mod:`app.session.config` (the file), :mod:`app.session.bus` (events, joints, the bus),
:mod:`app.session.loop` (the loop), :mod:`app.session.summary` (latency, rate, memory),
:class:`app.pipeline.sinks.EstimateFiles` (estimate.txt, status.csv). Import the public names from here.

The loop (:func:`run_session`), one thread (the tracker's GL context lives on it):

1. Sources push from their own threads through the *bus*, which validates each frame (size,
   dtype, finite, non-negative, increasing stamp) and each joint sample (finite, increasing),
   rejects bad ones with a logged event, hands good ones to the sinks (the recorder queues every
   one of them), and keeps only the newest frames for the tracker (a bounded drop-oldest queue:
   the tracker works on the latest frame, and says how many it skipped).
2. For each frame the joint buffer is interpolated at the frame's stamp (waiting up to
   ``robot_wait_s`` for the robot to catch up): ``T_base_camera = FK(q) T_flange_camera``.
3. The tracker steps; the status is capped at ``uncertain`` without a camera pose and at ``lost``
   after the tracker's ``recovery.after_uncertain_s`` without one (one missing-pose clock, the lifecycle's patience; it was the session's
   ``loop.robot_lost_s`` too before issue 32); with no frames for ``stall_timeout_s`` the loop emits
   ``lost`` estimates (the projector shows no template) until frames return.
4. Frame-to-estimate latency (host time at the estimate minus the frame's capture stamp) is
   measured per frame, logged, and summarised (median, p99; per stage: capture->arrival, queue
   wait, tracker, sinks; the first and last 10 s); the frames dropped are counted where they go
   (a trial player behind its schedule, the tracker queue), and the memory (RSS) sampled.

Ctrl-C (or SIGTERM) ends the loop; sources stop, sinks flush and close, the summary is written.
"""
from __future__ import annotations

from app.session.bus import Bus, EventLog, JointBuffer
from app.session.config import (FORMAT, LoopConfig, PluginSpec, SessionConfig, load_session, parse_session,
                                resolve_session)
from app.pipeline.sinks import EstimateFiles
from app.session.loop import LiveLoop, run_session
from app.session.summary import LatencyLog, SessionResult, rss_mb

__all__ = ["Bus", "EventLog", "JointBuffer", "FORMAT", "LoopConfig", "PluginSpec", "SessionConfig", "load_session",
           "parse_session", "resolve_session", "EstimateFiles", "LiveLoop", "run_session", "LatencyLog",
           "SessionResult", "rss_mb"]
