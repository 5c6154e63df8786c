"""The whole tracker's rate beside the ICP baseline (``osteonav bench-rate --whole``, issue 35).

On one trial (a CT-crest ``static_clear`` trial simulated once into a cache, or the user's), the
default tracker's whole ``DepthTracker.process`` (filter, refinement, status, and the recovery's
wide search when it runs) and the Open3D point-to-plane ICP baseline (app/baselines/icp.py, the
bench's ``icp`` configuration) process the same frames, frame by frame in turn, so a loaded machine
slows both alike:

- frames/s of each, from the wall time of its ``process`` calls (``fps``), and the process CPU time
  per frame (``cpu_ms``, all threads: Open3D's and numba's included), which other jobs on the
  machine do not inflate; the ratios ``tracker fps / ICP fps`` (``ratio``) and ICP's CPU per frame
  over the tracker's (``cpu_ratio``);
- the tracker's split per stage from its own timings (``DepthTracker.mean_timings_ms``: the filter's
  stages, ``refine``, ``recovery_search``; the backend's sub-stages of the likelihood apart), each
  as ms per frame and as a share of the frame's wall time; the rest (status, bookkeeping) is
  ``other``;
- counts: frames timed, frames the refinement ran on, frames that ran a wide search (their share),
  and each engine's statuses (an ICP that has lost the bone stops costing: its rate says so);
- the tracker once per ``filter.stages`` mode (app/pipeline/stages.py; default ``serial`` and
  ``parallel``), each its own DepthTracker on the same frames, in turn (their order swapped every
  frame): a row each, ``stages_ratio`` (parallel frames/s over serial) and ``stages_cpu_ratio``
  (parallel CPU per frame over serial), ``stages_main_cpu_ratio`` (the calling thread's CPU per frame,
  ``main_cpu_ms``, serial over parallel: the frame's work left on the calling thread, the rest running on numba's
  threads and the stage worker; a lower bound of the frame's wall time, so the ratio is the most
  the stages gain when the other work hides entirely on a free second core, and other jobs on the
  machine do not inflate it), and whether their outputs were identical on every frame,
  warm-up included (pose bit for bit, status, reasons, state: ``stages_identical``,
  ``stages_differing_frames``). ``tracker`` is the row of the configured mode (``filter.stages``
  resolved), which the ratio to ICP uses. The worker's refinement beside the filter's step is
  ``overlapped_ms`` (``refine_ahead``), not a share of the frame: it ran during the filter's stages.

The first ``warmup`` frames (numba's first calls, Open3D's set-up) run for both and are not timed.
Ratios measured in one run are stable on a noisy machine; absolute rates are not.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from app.config import TrackerConfig, load_config

SCENARIO = "static_clear"
SEED = 0
SEARCH_STAGE = "recovery_search"     # DepthTracker's stage for the recovery's wide search
REFINE_STAGE = "refine"
OVERLAPPED_STAGES = ("refine_ahead",)  # DepthTracker's stages run beside others (app/pipeline/stages.py)
STAGE_MODES = ("serial", "parallel")


def default_crest() -> Path | None:
    """The first shared CT crest mesh (``../shared/data/pelvis/crest_*.ply``), or None when absent."""
    from app.bench.trials import pelvis_crest_meshes

    meshes = pelvis_crest_meshes()
    return meshes[0] if meshes else None


def simulated_trial(mesh: Path, seconds: float, cache: Path) -> Path:
    """A ``static_clear`` trial of ``mesh``, simulated once into ``cache`` (reused while valid)."""
    from app.bench.trials import _cache_valid
    from app.sim.sensors import DEFAULT_SENSOR, parse_sensor, sensor_to_dict
    from app.sim.simulator import simulate

    out = Path(cache) / f"{Path(mesh).stem}-{SCENARIO}-{seconds:g}s"
    if not _cache_valid(out, SCENARIO, seconds, SEED, Path(mesh), sensor_to_dict(parse_sensor(DEFAULT_SENSOR))):
        simulate(out, mesh_path=mesh, scenario_name=SCENARIO, seconds=seconds, seed=SEED, overwrite=True)
    return out


def measure(trial: str | Path, config: TrackerConfig | None = None, frames: int | None = None, warmup: int = 3,
            progress=None, stages: tuple[str, ...] = STAGE_MODES) -> dict:
    """The rows of one run over ``trial`` (module docstring): ``{'trial', 'frames', 'tracker', 'icp', 'ratio',
    'stages', ...}``; ``stages``: the ``filter.stages`` modes to run the tracker in, side by side."""
    from dataclasses import replace

    from app.pipeline.stages import stages_mode
    from app.baselines.icp import ICPTracker
    from app.bench.configs import resolve_configs
    from app.pipeline.replay import known_plan
    from app.pipeline.tracker import DepthTracker, use_plan
    from app.trial.reader import open_trial

    config = config or load_config(None)
    reader = open_trial(trial)
    if reader.meta.initial_pose is None:
        raise ValueError(f"{trial}: the trial has no initial_pose to start the trackers from")
    n = len(reader) if frames is None else min(len(reader), warmup + int(frames))
    if n <= warmup:
        raise ValueError(f"{trial}: {len(reader)} frames, not more than the {warmup} warm-up frames")
    mesh = reader.load_mesh()
    camera = reader.meta.camera
    T_base_camera, valid = reader.camera_poses()
    modes = tuple(dict.fromkeys(stages))
    if not modes or any(m not in STAGE_MODES for m in modes):
        raise ValueError(f"stages: one or more of {', '.join(STAGE_MODES)}, got {stages!r}")
    refine = config.refine.enabled
    trackers, runs = {}, {}
    try:
        for mode in modes:
            tracker = trackers[mode] = DepthTracker(replace(config, stages=mode), mesh, camera)
            tracker.start(reader.meta.initial_pose)
            tracker.set_point_prior(reader.meta.point_prior)
            use_plan(tracker, known_plan(None, mesh)[0])          # as replay: the status's template points
            runs[mode] = _Timed(tracker)
        icp = ICPTracker(resolve_configs(["icp"])[0].icp, mesh, camera)
        icp.start(reader.meta.initial_pose)
        runs["icp"] = _Timed(icp)
        differing = 0
        for i in range(n):
            depth = reader.read_depth(i)
            pose = T_base_camera[i] if valid[i] else None
            if i == warmup:                                # the timed frames start here
                for tracker in trackers.values():
                    tracker._timings.clear()
                    tracker._frames = 0
            order = list(modes) if i % 2 == 0 else list(reversed(modes))     # neither always first
            outputs = {m: runs[m].process(depth, float(reader.stamps[i]), pose, timed=i >= warmup) for m in order}
            runs["icp"].process(depth, float(reader.stamps[i]), pose, timed=i >= warmup)
            differing += not _same_outputs([outputs[m] for m in modes])
            if progress:
                progress(i + 1, n)
    finally:
        for engine in [*trackers.values(), *([runs["icp"].engine] if "icp" in runs else [])]:
            engine.release()
    rows = {m: _tracker_row(runs[m], trackers[m], replace(config, stages=m)) for m in modes}
    configured = stages_mode(config.stages, refine)
    row_t = rows[configured] if configured in rows else rows[modes[0]]
    row_i = runs["icp"].row()
    both = "serial" in rows and "parallel" in rows
    return {"trial": str(trial), "mesh": str(reader.mesh_path), "frames": n - warmup, "warmup": warmup,
            "tracker": row_t, "icp": row_i, "ratio": row_t["fps"] / row_i["fps"] if row_i["fps"] > 0 else None,
            "cpu_ratio": row_i["cpu_ms"] / row_t["cpu_ms"] if row_t["cpu_ms"] > 0 else None,
            "stages": rows, "configured_stages": configured if configured in rows else modes[0],
            "stages_ratio": rows["parallel"]["fps"] / rows["serial"]["fps"] if both else None,
            "stages_cpu_ratio": rows["parallel"]["cpu_ms"] / rows["serial"]["cpu_ms"] if both else None,
            "stages_main_cpu_ratio": (rows["serial"]["main_cpu_ms"] / rows["parallel"]["main_cpu_ms"]
                                      if both and rows["parallel"]["main_cpu_ms"] > 0 else None),
            "stages_identical": differing == 0, "stages_differing_frames": differing, "stages_compared_frames": n}


def _same_outputs(outputs: list) -> bool:
    """Whether the trackers' outputs of one frame are the same: the pose bit for bit, the status, its
    reasons and the lifecycle's state (what estimate.txt and status.csv are written from)."""
    first = outputs[0]
    return all(np.array_equal(o.T_base_bone, first.T_base_bone) and o.status == first.status
               and o.reasons == first.reasons and o.state == first.state for o in outputs[1:])


class _Timed:
    """One engine's timed ``process`` calls: wall and process CPU seconds, frames, what each returned."""

    def __init__(self, engine):
        self.engine = engine
        self.wall = self.cpu = self.thread_cpu = 0.0
        self.frames = 0
        self.refined = 0
        self.searched = 0
        self.statuses: dict[str, int] = {}

    def _search_s(self) -> float:
        """The engine's wide-search seconds so far (DepthTracker's own timings; 0 for ICP)."""
        return getattr(self.engine, "_timings", {}).get(SEARCH_STAGE, 0.0)

    def process(self, depth, stamp, pose, timed: bool):
        """The engine's ``process`` of one frame, timed when ``timed``; its output."""
        searched_before = self._search_s()
        t0, c0, m0 = time.perf_counter(), time.process_time(), time.thread_time()
        result = self.engine.process(depth, stamp, pose)
        wall, cpu, main = time.perf_counter() - t0, time.process_time() - c0, time.thread_time() - m0
        if not timed:
            return result
        self.wall += wall
        self.cpu += cpu
        self.thread_cpu += main
        self.frames += 1
        self.refined += bool(getattr(result, "refined", False))
        status = str(getattr(result.status, "value", result.status))
        self.statuses[status] = self.statuses.get(status, 0) + 1
        self.searched += self._search_s() > searched_before
        return result

    def row(self) -> dict:
        frame_ms = 1e3 * self.wall / max(self.frames, 1)
        return {"frames": self.frames, "wall_s": self.wall, "frame_ms": frame_ms,
                "fps": 1e3 / frame_ms if frame_ms > 0 else float("inf"),
                "cpu_ms": 1e3 * self.cpu / max(self.frames, 1),
                "main_cpu_ms": 1e3 * self.thread_cpu / max(self.frames, 1), "status_counts": dict(self.statuses)}


def _tracker_row(run: _Timed, tracker, config: TrackerConfig) -> dict:
    """The tracker's row: rate, counts, and its stage split (ms per frame, share of the frame's wall time)."""
    row = run.row()
    stages = tracker.mean_timings_ms()
    backend = f"{tracker.backend_name}_"
    overlapped = {k: stages.pop(k) for k in OVERLAPPED_STAGES if k in stages}
    top = {k: v for k, v in stages.items() if not k.startswith(backend)}
    shares = {k: v / row["frame_ms"] for k, v in top.items()} if row["frame_ms"] > 0 else {}
    row.update({
        "description": f"{config.particles} particles at {config.resolution[0]}x{config.resolution[1]}, "
                       f"{tracker.backend_name} backend, refinement {'on' if tracker.refined_track is not None else 'off'}, "
                       f"stages {tracker.stages}",
        "stages_mode": tracker.stages, "overlapped_ms": overlapped,
        "timed_frames_in_stages": tracker._frames,
        "stages_ms": top, "backend_stages_ms": {k: v for k, v in stages.items() if k.startswith(backend)},
        "stage_shares": shares, "other_share": max(0.0, 1.0 - sum(shares.values())),
        "refined_frames": run.refined, "search_frames": run.searched,
        "search_share": run.searched / max(run.frames, 1),
    })
    return row


def table(result: dict) -> str:
    """Fixed-width table: the tracker's rows (one per stages mode) and ICP's, the ratios, then the stage
    split of the configured mode's tracker (``*``)."""
    t, i = result["tracker"], result["icp"]
    rows = result.get("stages") or {t.get("stages_mode", "-"): t}
    configured = result.get("configured_stages")
    lines = [f"{'engine':<19} {'frames':>6} {'fps':>7} {'frame ms':>9} {'cpu ms':>8} {'main cpu':>9}  notes", "-" * 92]
    for mode, row in rows.items():
        mark = " *" if mode == configured and len(rows) > 1 else ""
        lines.append(f"{'tracker ' + mode + mark:<19} {row['frames']:>6} {row['fps']:>7.1f} {row['frame_ms']:>9.2f} "
                     f"{row['cpu_ms']:>8.2f} {row['main_cpu_ms']:>9.2f}  refined {row['refined_frames']}/{row['frames']}, wide search on "
                     f"{row['search_frames']} ({100 * row['search_share']:.0f} %), status {_counts(row['status_counts'])}")
    lines.append(f"{'icp':<19} {i['frames']:>6} {i['fps']:>7.1f} {i['frame_ms']:>9.2f} {i['cpu_ms']:>8.2f} {i['main_cpu_ms']:>9.2f}  "
                 f"Open3D point-to-plane, status {_counts(i['status_counts'])}")
    if result.get("stages_ratio") is not None:
        same = (f"outputs identical on all {result['stages_compared_frames']} frames" if result["stages_identical"] else
                f"OUTPUTS DIFFER on {result['stages_differing_frames']} of {result['stages_compared_frames']} frames")
        main = result.get("stages_main_cpu_ratio")
        lines.append(f"parallel / serial stages: {result['stages_ratio']:.2f}x the frames/s, "
                     f"{result['stages_cpu_ratio']:.2f}x the CPU per frame, the calling thread's CPU per frame "
                     f"{'-' if main is None else f'{1 / main:.2f}'}x (up to {'-' if main is None else f'{main:.2f}'}x "
                     f"the frames/s with a second core free); {same}")
    elif len(rows) > 1:
        same = "identical" if result["stages_identical"] else "DIFFERENT"
        lines.append(f"outputs of the modes: {same}")
    ratio = result["ratio"]
    cpu_ratio = result.get("cpu_ratio")
    which = f"tracker{' ' + configured if configured and len(rows) > 1 else ''}"
    lines.append(f"{which} / ICP: {'-' if ratio is None else f'{ratio:.2f}'}x the frames/s on the same "
                 f"{t['frames']} frames ({'-' if cpu_ratio is None else f'{cpu_ratio:.2f}'}x by CPU time per frame)")
    lost = i["status_counts"].get("lost", 0)
    if lost:
        lines.append(f"note: ICP was lost on {lost} of {i['frames']} frames; a lost ICP stops early (too few points "
                     "near its pose), so its rate there is not that of a tracking ICP")
    lines.append("")
    lines.append(f"{'tracker stage':<18} {'ms/frame':>9} {'share':>7}")
    lines.append("-" * 36)
    for stage, ms in sorted(t["stages_ms"].items(), key=lambda kv: -kv[1]):
        lines.append(f"{stage:<18} {ms:>9.2f} {100 * t['stage_shares'][stage]:>6.1f}%")
    lines.append(f"{'other (status...)':<18} {t['frame_ms'] * t['other_share']:>9.2f} {100 * t['other_share']:>6.1f}%")
    for stage, ms in t.get("overlapped_ms", {}).items():
        lines.append(f"{stage:<18} {ms:>9.2f}   (on the stage worker, beside the filter's stages)")
    return "\n".join(lines)


def _counts(counts: dict) -> str:
    """'ok 12, lost 3' from a status -> frames mapping."""
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) or "-"
