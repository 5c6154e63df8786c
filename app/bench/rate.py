"""The filter's rate benchmark (``osteonav bench-rate``): frames per second and where the time goes.

For each particle count N and filter resolution, every requested likelihood backend (``gl``:
batched GL rendering + compute shader, on llvmpipe without a GPU; ``cpu``: the numba z-buffer of
app/render/cpu_raster.py) runs one after the other on the same synthetic sequence (the crest at
0.42 m, measured depth = its rendering plus noise), so a loaded machine slows them alike:
- the full filter step (predict, likelihood, weight/resample, estimate) timed as a whole without
  extra synchronisation: ``fps``; and the CPU time of this process per frame over all its threads
  (``process_cpu_ms``, llvmpipe's threads included), which other jobs on the machine do not inflate;
- the same with the backend synchronised after each stage, for the split per stage (``stages_ms``:
  the filter's stages and the backend's own, prefixed with its name);
- the backend's ``log_likelihood`` of N poses alone (``backend_ms``) and, for gl, the bare render
  of the N poses (one instanced draw), the reference of the overhead ratio (issue 3);
- for cpu, the first kernel calls of the process (numba compile, or loading numba's on-disk cache:
  ``numba_cache``) in ``first_call_s``, reported apart from the rate;
- with ``refine.enabled``, the local refinement's time per frame (``stages_ms['refine']``, the
  tracker's ``DepthTracker._refine``, wall) and its process CPU time (``refine_cpu_ms``: the
  tracker's ``refined_track.update`` calls, timed by wrapping them in the synchronised pass), and
  what it adds to the rest of the frame (issue 12's "at most 30 %"): ``refine_added`` =
  refine_cpu / (CPU per frame - refine_cpu), in CPU time, which other jobs on the machine do not
  inflate, and ``refine_added_wall`` from the wall times; None when disabled.
Ratios between backends measured in one run are stable on noisy machines; absolute times are not.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from app.config import TrackerConfig, load_config
from app.depth_image import downsample_nearest
from app.geometry import quaternion as quat
from app.geometry import se3

BACKENDS = ("cpu", "gl")
PARTICLES = (200, 700, 1500)
RESOLUTIONS = ((80, 60), (100, 75), (160, 120))
FILTER_STAGES = ("predict", "likelihood", "weight", "resample", "estimate")
REFINE_STAGE = "refine"   # DepthTracker's stage when refine.enabled (app/pipeline/tracker.py)


def _scene():
    T_base_camera = np.eye(4)
    T_base_bone = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([3.0, 0.1, 0.0]))), np.array([0.0, 0.0, 0.42]))
    return T_base_camera, T_base_bone


def _measured_depth(backend, T_base_bone, camera_full) -> np.ndarray:
    """The true pose rendered at the filter resolution, upsampled by repetition to full resolution
    (the same low-resolution input as a full-resolution rendering), 0.6 m table behind it."""
    small = backend.render_depth(T_base_bone[None])[0]
    h, w = camera_full.height, camera_full.width
    rows = np.minimum((np.arange(h) * small.shape[0]) // h, small.shape[0] - 1)
    cols = np.minimum((np.arange(w) * small.shape[1]) // w, small.shape[1] - 1)
    depth_full = small[np.ix_(rows, cols)]
    return np.where(depth_full > 0, depth_full, 0.6).astype(np.float32)


def _time_calls(fn, repeats: int) -> float:
    """Mean ms of ``fn()`` over ``repeats`` calls (after one untimed call)."""
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return 1e3 * (time.perf_counter() - t0) / repeats


def measure(config: TrackerConfig, mesh, camera_full, frames: int = 30, warmup: int = 5, seed: int = 0) -> dict:
    """Timings (ms) of one configuration (``config.backend`` must be 'gl' or 'cpu')."""
    from app.pipeline.tracker import DepthTracker
    from app.render.cpu_likelihood import first_call_seconds

    rng = np.random.default_rng(seed)
    T_base_camera, T_base_bone = _scene()
    t0 = time.perf_counter()
    tracker = DepthTracker(config, mesh, camera_full)
    setup_s = time.perf_counter() - t0
    backend = tracker.backend
    depth_full = _measured_depth(backend, T_base_bone, camera_full)
    tracker.start(T_base_bone)
    stamp = 0.0
    for _ in range(warmup):
        stamp += 1 / 90
        tracker.process(depth_full + rng.normal(0, 5e-4, depth_full.shape).astype(np.float32), stamp, T_base_camera)
    backend.sync()
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(frames):
        stamp += 1 / 90
        tracker.process(depth_full, stamp, T_base_camera)
    backend.sync()
    full_ms = 1e3 * (time.perf_counter() - t0) / frames
    process_cpu_ms = 1e3 * (time.process_time() - c0) / frames
    backend.profile = True          # stage split: the GL backend waits after each stage
    tracker._timings.clear()
    tracker._frames = 0
    refine_cpu_s = _time_refinement_cpu(tracker)
    for _ in range(frames):
        stamp += 1 / 90
        tracker.process(depth_full, stamp, T_base_camera)
    stages = tracker.mean_timings_ms()
    backend.profile = False
    refine_ms = stages.get(REFINE_STAGE) if config.refine.enabled else None
    refine_cpu_ms = 1e3 * refine_cpu_s[0] / frames if tracker.refined_track is not None else None
    poses = se3.inverse(T_base_camera) @ np.repeat(T_base_bone[None], config.particles, axis=0)
    poses = poses @ se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.02, (config.particles, 3))),
                                        rng.normal(0, 0.003, (config.particles, 3)))
    depth_small = downsample_nearest(depth_full, *config.resolution)
    backend_ms = _time_calls(lambda: (backend.log_likelihood(poses, depth_small), backend.sync()), frames)
    bare_render_ms = None
    if tracker.backend_name == "gl":
        bare_render_ms = _time_calls(lambda: (backend.renderer.render(poses), backend.sync()), frames)
    row = {
        "backend": tracker.backend_name, "particles": config.particles,
        "resolution": f"{config.resolution[0]}x{config.resolution[1]}", "mesh_triangles": len(tracker.mesh_faces),
        "full_frame_ms": full_ms, "fps": 1e3 / full_ms, "process_cpu_ms": process_cpu_ms, "backend_ms": backend_ms, "bare_render_ms": bare_render_ms,
        "overhead_fraction": None if bare_render_ms is None else max(0.0, 1.0 - bare_render_ms / full_ms),
        "stages_ms": stages, "setup_s": setup_s, "description": tracker.gl_description,
        "refine_ms": refine_ms, "refine_cpu_ms": refine_cpu_ms,
        "refine_added": _refine_added(refine_cpu_ms, process_cpu_ms), "refine_added_wall": _refine_added(refine_ms, full_ms),
        "first_call_s": first_call_seconds() if tracker.backend_name == "cpu" else None,
        "numba_cache": _numba_cache_state() if tracker.backend_name == "cpu" else None,
    }
    tracker.release()
    return row


def _time_refinement_cpu(tracker) -> list[float]:
    """[process CPU seconds] that the tracker's refinement calls add up to from now on (a one-element
    list the wrapper updates); [0.0] and nothing wrapped when the refinement is off."""
    total = [0.0]
    track = tracker.refined_track
    if track is None:
        return total
    update = track.update

    def timed(*args, **kwargs):
        c0 = time.process_time()
        try:
            return update(*args, **kwargs)
        finally:
            total[0] += time.process_time() - c0

    track.update = timed
    return total


def _refine_added(refine_ms: float | None, frame_ms: float) -> float | None:
    """What the refinement adds to the rest of the frame: refine / (frame - refine); None without it.
    The refinement's time comes from the synchronised pass, the frame's from the timed one (both
    per frame, both wall or both CPU)."""
    if refine_ms is None or frame_ms <= refine_ms:
        return None
    return refine_ms / (frame_ms - refine_ms)


def _numba_cache_state() -> str:
    """'hit' when the fused kernel came from numba's on-disk cache in this process, else 'compiled'."""
    from app.render import cpu_raster

    hits = sum(cpu_raster.batch.stats.cache_hits.values())
    return "hit" if hits else "compiled"


def run(particles=PARTICLES, resolutions=RESOLUTIONS, frames: int = 30, base: TrackerConfig | None = None,
        progress=None, backends=BACKENDS) -> list[dict]:
    """One row per (N, resolution, backend); the backends of one (N, resolution) run back to back."""
    from app.mesh import load_mesh
    from app.sim.simulator import D415_640x480, DEFAULT_MESH

    base = base or load_config(None)
    mesh = load_mesh(DEFAULT_MESH)
    results = []
    for n in particles:
        for res in resolutions:
            for name in backends:
                config = replace(base, particles=int(n), resolution=tuple(res), backend=name)
                results.append(measure(config, mesh, D415_640x480, frames=frames))
                if progress:
                    progress(results[-1])
    return results


def table(results: list[dict]) -> str:
    """Fixed-width table: one line per row, with the speed-up over gl of the same N and resolution;
    with the refinement on in any row, its stage (wall ms) and ``refine_added`` (CPU, as %) as two more columns."""
    gl_fps = {(r["particles"], r["resolution"]): r["fps"] for r in results if r["backend"] == "gl"}
    stage_names = FILTER_STAGES + ((REFINE_STAGE,) if any(r.get("refine_ms") is not None for r in results) else ())
    header = (f"{'backend':<7} {'N':>5} {'res':>8} {'fps':>7} {'x gl':>6} {'frame ms':>9} {'cpu ms':>8} {'backend ms':>10}  "
              + " ".join(f"{s:>10}" for s in stage_names) + (f" {'refine +%cpu':>12}" if REFINE_STAGE in stage_names else ""))
    lines = [header, "-" * len(header)]
    for r in results:
        ref = gl_fps.get((r["particles"], r["resolution"]))
        ratio = f"{r['fps'] / ref:>6.1f}" if ref else f"{'-':>6}"
        stages = r["stages_ms"]
        added = r.get("refine_added")
        lines.append(f"{r['backend']:<7} {r['particles']:>5} {r['resolution']:>8} {r['fps']:>7.1f} {ratio} "
                     f"{r['full_frame_ms']:>9.2f} {r['process_cpu_ms']:>8.2f} {r['backend_ms']:>10.2f}  "
                     + " ".join(f"{stages.get(s, float('nan')):>10.2f}" for s in stage_names)
                     + ("" if REFINE_STAGE not in stage_names else f" {'-' if added is None else f'{100 * added:.0f}':>12}"))
    return "\n".join(lines)
