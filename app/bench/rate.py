"""The filter's rate benchmark (``osteonav bench-rate``): frames per second and where the time goes.

For each particle count N and filter resolution, one run on the same GL context:
- the full filter step (predict, render, likelihood, read-back, weight/resample, estimate) over a
  synthetic sequence (the crest at 0.42 m, measured depth = its rendering plus noise), timed as a
  whole without extra synchronisation;
- the same with a GPU sync after each stage, for the split per stage;
- the bare render of the same N poses (one instanced draw, synchronised), the reference for the
  overhead ratio: overhead = 1 - bare render / full frame (issue 3: at most 25 %).
Ratios are stable on noisy machines; absolute times are not. Results go to a table and JSON.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from app.config import TrackerConfig, load_config
from app.geometry import quaternion as quat
from app.geometry import se3

PARTICLES = (200, 700, 1500)
RESOLUTIONS = ((80, 60), (100, 75), (160, 120))


def _scene(camera_full, rng):
    T_base_camera = np.eye(4)
    T_base_bone = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([3.0, 0.1, 0.0]))), np.array([0.0, 0.0, 0.42]))
    return T_base_camera, T_base_bone


def measure(config: TrackerConfig, mesh, camera_full, frames: int = 30, warmup: int = 5, seed: int = 0) -> dict:
    """Timings (ms) of one configuration: full frame, per stage, bare render; fps and overhead."""
    from app.pipeline.tracker import DepthTracker

    rng = np.random.default_rng(seed)
    T_base_camera, T_base_bone = _scene(camera_full, rng)
    tracker = DepthTracker(config, mesh, camera_full)
    backend = tracker.backend
    # the measured image: the true pose rendered at full resolution would need a second renderer;
    # rendering at the filter resolution and upsampling by repetition gives the same low-res input
    small = backend.render_depth(T_base_bone[None])[0]
    h, w = camera_full.height, camera_full.width
    rows = np.minimum((np.arange(h) * small.shape[0]) // h, small.shape[0] - 1)
    cols = np.minimum((np.arange(w) * small.shape[1]) // w, small.shape[1] - 1)
    depth_full = small[np.ix_(rows, cols)]
    depth_full = np.where(depth_full > 0, depth_full, 0.6).astype(np.float32)
    tracker.start(T_base_bone)
    stamp = 0.0
    for _ in range(warmup):
        stamp += 1 / 90
        tracker.process(depth_full + rng.normal(0, 5e-4, depth_full.shape).astype(np.float32), stamp, T_base_camera)
    t0 = time.perf_counter()
    for _ in range(frames):
        stamp += 1 / 90
        tracker.process(depth_full, stamp, T_base_camera)
    tracker.backend.ctx.finish()
    full_ms = 1e3 * (time.perf_counter() - t0) / frames
    # stage split (synchronised)
    backend.profile = True
    tracker._timings.clear()
    tracker._frames = 0
    for _ in range(frames):
        stamp += 1 / 90
        tracker.process(depth_full, stamp, T_base_camera)
    stages = tracker.mean_timings_ms()
    backend.profile = False
    # bare render of N poses
    poses = se3.inverse(T_base_camera) @ np.repeat(T_base_bone[None], config.particles, axis=0)
    poses = poses @ se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.02, (config.particles, 3))),
                                        rng.normal(0, 0.003, (config.particles, 3)))
    backend.renderer.render(poses)
    backend.ctx.finish()
    t0 = time.perf_counter()
    for _ in range(frames):
        backend.renderer.render(poses)
        backend.ctx.finish()
    render_ms = 1e3 * (time.perf_counter() - t0) / frames
    description = tracker.gl_description
    tracker.release()
    return {
        "particles": config.particles, "resolution": list(config.resolution), "mesh_triangles": len(tracker.mesh_faces),
        "full_frame_ms": full_ms, "fps": 1e3 / full_ms, "bare_render_ms": render_ms,
        "overhead_fraction": max(0.0, 1.0 - render_ms / full_ms), "stages_ms": stages, "gl": description,
    }


def run(particles=PARTICLES, resolutions=RESOLUTIONS, frames: int = 30, base: TrackerConfig | None = None,
        progress=None) -> list[dict]:
    from app.mesh import load_mesh
    from app.sim.simulator import D415_640x480, DEFAULT_MESH

    base = base or load_config(None)
    mesh = load_mesh(DEFAULT_MESH)
    results = []
    for n in particles:
        for res in resolutions:
            config = replace(base, particles=int(n), resolution=tuple(res))
            results.append(measure(config, mesh, D415_640x480, frames=frames))
            if progress:
                progress(results[-1])
    return results


def table(results: list[dict]) -> str:
    stage_names = ("predict", "gl_render", "gl_likelihood", "gl_readback", "resample", "estimate")
    header = f"{'N':>5} {'res':>8} {'fps':>7} {'frame ms':>9} {'render ms':>10} {'overhead':>9}  " + \
        " ".join(f"{s.replace('gl_', ''):>10}" for s in stage_names)
    lines = [header, "-" * len(header)]
    for r in results:
        stages = r["stages_ms"]
        lines.append(
            f"{r['particles']:>5} {r['resolution'][0]:>4}x{r['resolution'][1]:<3} {r['fps']:>7.1f} {r['full_frame_ms']:>9.2f} "
            f"{r['bare_render_ms']:>10.2f} {100 * r['overhead_fraction']:>8.0f}%  "
            + " ".join(f"{stages.get(s, float('nan')):>10.2f}" for s in stage_names)
        )
    return "\n".join(lines)
