"""``osteonav bench``: every configuration on every trial, side by side, with the field's metrics.

Usage::

    from app.bench import bench
    configs = bench.resolve_configs(["A_cpu", "icp", "my_tuned.yaml"])      # built-in names or files
    trials = bench.standard_trials(cache="recordings/bench", seconds=3.0)   # or bench.recorded_trials(dirs)
    rows = bench.run_bench(configs, trials, jobs=1)
    print(bench.table(rows)); bench.write_json(rows, "bench.json"); bench.plot(rows, "plots/")

**Configurations** are YAML files (built-in ones in ``configs/bench/``, copy and edit them). A
particle-filter file is an ordinary tracker configuration (:func:`app.config.load_config`); it may
say ``tracker: particle_filter`` on top. An ICP file says ``tracker: icp`` and has an ``icp``
section with the fields of :class:`app.baselines.icp.ICPParams` (:func:`load_icp_params`).

**Trials**: ``--trials DIR...`` (recorded or simulated trials with ``groundtruth.txt``) or, by
default, the standard scenarios (:data:`app.sim.scenarios.STANDARD`) simulated for the default
mesh and for each ``crest_*.ply`` of ``../shared/data/pelvis`` (skipped when absent), cached in
``recordings/bench/<mesh>/<scenario>`` and re-simulated only when the scenario, its duration, the
seed or the mesh changed.

**Columns** (per configuration x trial; errors are of the estimate in the robot base frame
against ``groundtruth.txt``, on every processed frame, whatever the status):

- ``fps``: processed frames per second of wall time of the whole replay loop (PNG decoding, the
  tracker, the per-frame ADD) on this machine; with ``--jobs`` > 1 runs share the CPU.
- ``ADD med / p95`` (mm), ``rot med / p95`` (deg): :mod:`app.metrics`; ADD-S, MDD-S, the
  translation error and VSD are in the JSON, VSD recall in the table.
- ``VSD rec``: fraction of frames with e_VSD < 0.3 (tau = 20 mm), the model rendered at
  :data:`VSD_RESOLUTION` at the estimate and the truth against the measured depth.
- ``lost %``: frames with ADD > 10 mm (the track is gone, whatever the status says).
- ``ok %``: frames whose status is ``ok``.
- ``danger``: frames with status ``ok`` while ADD > 5 mm: the confident wrong pose, which must be 0.
- ``jitter`` (mm / deg): while the bone is static, the RMS of the estimate's frame-to-frame
  change ``|t_k - t_{k-1}|`` and ``angle(R_{k-1}^T R_k)`` over consecutive frame pairs whose
  ground-truth poses are equal (within 1 um / 1e-5 rad), after the first :data:`JITTER_SETTLE_S`
  s (the initial convergence is not jitter). The truth does not move, so any change is jitter.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from app.errors import ConfigError
from app.metrics import DANGEROUS_ADD_MM, LOST_ADD_MM

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
BUILTIN_DIR = REPO / "configs" / "bench"
BUILTIN_ORDER = ("osteonav_default", "A_cpu", "A_cadaver", "thesis_blockwise", "thesis_joint", "thesis_complex", "icp")
PELVIS_DIR = REPO.parent / "shared" / "data" / "pelvis"
DEFAULT_CACHE = Path("recordings") / "bench"
QUICK_SCENARIOS = ("static_clear", "bone_moves")
QUICK_CONFIGS = ("osteonav_default", "A_cpu", "icp")   # ours, publication A's, the ICP baseline
QUICK_STATIC_S = 1.5


def quick_seconds(scenarios=QUICK_SCENARIOS) -> dict[str, float]:
    """``--quick`` trial lengths: 1.5 s, or until the scenario's last bone move has ended (bone_moves:
    1.5 + 2.0 = 3.5 s), so that a moving trial really moves within the quick run."""
    from app.sim.scenarios import get_scenario

    out = {}
    for name in scenarios:
        moves = get_scenario(name).bone_motion
        out[name] = max([QUICK_STATIC_S] + [start + duration for start, duration, *_ in moves])
    return out


def _seconds_for(seconds: float | dict | None, scenario: str | None = None) -> float | None:
    """A trial length from ``seconds``: a number for every trial, or a mapping by scenario name."""
    if isinstance(seconds, dict):
        return float(seconds[scenario]) if scenario in seconds else (max(seconds.values()) if scenario is None else None)
    return None if seconds is None else float(seconds)
TRACKERS = ("particle_filter", "icp")
VSD_RESOLUTION = (160, 120)
JITTER_SETTLE_S = 0.5
STATIC_TRANSLATION_M = 1e-6
STATIC_ROTATION_RAD = 1e-5


# --------------------------------------------------------------------------- configurations

@dataclass
class BenchConfig:
    """One configuration to benchmark: a particle filter (``tracker``) or the ICP baseline (``icp``)."""

    name: str
    kind: str                        # 'particle_filter' | 'icp'
    tracker: Any = None              # app.config.TrackerConfig when kind == 'particle_filter'
    icp: Any = None                  # app.baselines.icp.ICPParams when kind == 'icp'
    source: str = ""

    def describe(self) -> str:
        if self.kind == "icp":
            return f"Open3D point-to-plane ICP at {self.icp.resolution[0]}x{self.icp.resolution[1]}"
        c = self.tracker
        extra = []
        if c.likelihood.occlusion != "exponential":
            extra.append(c.likelihood.occlusion)
        if c.likelihood.classification:
            extra.append("classification+L0")
        return (f"{c.particles} particles at {c.resolution[0]}x{c.resolution[1]}, {c.sampling}"
                + (f", {', '.join(extra)}" if extra else ""))


def builtin_configs() -> dict[str, Path]:
    """Built-in configuration files by name (file stem), in the documented order."""
    found = {p.stem: p for p in sorted(BUILTIN_DIR.glob("*.yaml"))}
    ordered = {name: found.pop(name) for name in BUILTIN_ORDER if name in found}
    ordered.update(found)
    return ordered


def resolve_configs(names=None) -> list[BenchConfig]:
    """BenchConfigs for built-in names (``A_cpu``) or YAML paths; all built-ins when ``names`` is empty."""
    builtins = builtin_configs()
    if not names:
        return [load_bench_config(path) for path in builtins.values()]
    configs = []
    for name in names:
        path = Path(name)
        if path.suffix in (".yaml", ".yml") or path.exists():
            configs.append(load_bench_config(path))
        elif name in builtins:
            configs.append(load_bench_config(builtins[name]))
        else:
            raise ConfigError("--configs", f"'{name}' is neither a built-in configuration "
                              f"({', '.join(builtins)}) nor an existing YAML file")
    seen = set()
    for c in configs:
        if c.name in seen:
            raise ConfigError("--configs", f"two configurations are named '{c.name}' (the file stem); rename one")
        seen.add(c.name)
    return configs


def load_bench_config(path: str | Path) -> BenchConfig:
    """Read a configuration file; ``tracker: icp`` selects the ICP baseline (module docstring)."""
    from app.config import config_from_dict

    path = Path(path)
    if not path.is_file():
        raise ConfigError("(file)", f"no such configuration file; built-in ones are in {BUILTIN_DIR}", source=str(path))
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError("(file)", f"not valid YAML: {exc}", source=str(path)) from None
    if not isinstance(data, dict):
        raise ConfigError("(top level)", f"expected a mapping, got {type(data).__name__}", str(path))
    data = dict(data)
    kind = data.pop("tracker", "particle_filter")
    if kind not in TRACKERS:
        raise ConfigError("tracker", f"{kind!r} is not one of: {', '.join(TRACKERS)}", str(path))
    if kind == "icp":
        return BenchConfig(path.stem, "icp", icp=load_icp_params(data, source=str(path)), source=str(path))
    return BenchConfig(path.stem, "particle_filter", tracker=config_from_dict(data, source=str(path)), source=str(path))


def load_icp_params(data: Any, source: str | None = None):
    """:class:`app.baselines.icp.ICPParams` from ``{'icp': {field: value}}`` (the ``tracker`` key removed).

    Raises ConfigError naming the dotted key for unknown sections or keys, wrong types and
    non-positive values.
    """
    from app.baselines.icp import ICPParams

    if not isinstance(data, dict):
        raise ConfigError("(top level)", f"expected a mapping, got {type(data).__name__}", source)
    unknown = set(data) - {"icp"}
    if unknown:
        raise ConfigError(sorted(map(str, unknown))[0], "unknown section of an ICP configuration; "
                          "valid: tracker, icp", source)
    values = data.get("icp") or {}
    if not isinstance(values, dict):
        raise ConfigError("icp", f"expected a mapping of keys, got {type(values).__name__} {values!r}", source)
    fields = {f.name: f for f in dataclasses.fields(ICPParams)}
    defaults = ICPParams()
    kwargs = {}
    for name, value in values.items():
        key = f"icp.{name}"
        if name not in fields:
            import difflib

            close = difflib.get_close_matches(str(name), list(fields), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ConfigError(key, f"unknown key{hint}; valid keys of 'icp': {', '.join(fields)}", source)
        default = getattr(defaults, name)
        if isinstance(default, tuple):
            ok = (isinstance(value, (list, tuple)) and len(value) == 2
                  and all(isinstance(v, int) and not isinstance(v, bool) and 8 <= v <= 4096 for v in value))
            if not ok:
                raise ConfigError(key, f"expected [width, height], two integers in [8, 4096], got {value!r}", source)
            value = (int(value[0]), int(value[1]))
        elif isinstance(default, int):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(key, f"expected an integer >= 1, got {value!r}", source)
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(key, f"expected a number > 0, got {value!r}", source)
            if name.endswith("fitness") and value > 1:
                raise ConfigError(key, f"a fitness is a fraction in (0, 1], got {value!r}", source)
            value = float(value)
        kwargs[name] = value
    return ICPParams(**kwargs)


# --------------------------------------------------------------------------- trials

@dataclass
class TrialSpec:
    """A trial to run: its directory and how to name it in the table."""

    path: str
    mesh: str
    scenario: str
    frames: int = 0
    max_frames: int | None = None

    @property
    def name(self) -> str:
        return f"{self.mesh}/{self.scenario}"


def pelvis_crest_meshes(folder: Path = PELVIS_DIR) -> list[Path]:
    """The ``crest_*.ply`` meshes of the shared pelvis folder; empty (with a log line) when absent."""
    if not folder.is_dir():
        log.info("no pelvis meshes at %s: benchmarking the default mesh only", folder)
        return []
    return sorted(folder.glob("crest_*.ply"))


def _cache_valid(trial: Path, scenario: str, seconds: float, seed: int, mesh_path: Path) -> bool:
    info_path = trial / "simulation.yaml"
    if not (trial / "trial.yaml").is_file() or not info_path.is_file() or not (trial / "groundtruth.txt").is_file():
        return False
    try:
        info = yaml.safe_load(info_path.read_text())
        from app.trial.reader import open_trial

        reader = open_trial(trial)
    except Exception:  # noqa: BLE001 -- any unreadable cache entry is simply re-simulated
        return False
    return (not reader.interrupted and info.get("seed") == seed
            and info.get("scenario", {}).get("name") == scenario
            and abs(float(info.get("scenario", {}).get("seconds", -1)) - seconds) < 1e-9
            and Path(info.get("mesh_source", "")).resolve() == mesh_path.resolve())


def _simulate_task(task: dict) -> dict:
    from app.sim.simulator import simulate

    summary = simulate(task["out"], mesh_path=task["mesh"], scenario_name=task["scenario"], seconds=task["seconds"],
                       seed=task["seed"], overwrite=True)
    return {"out": task["out"], "frames": summary.frames}


def standard_trials(cache: str | Path = DEFAULT_CACHE, scenarios=None, seconds: float | dict | None = None,
                    meshes=None, seed: int = 0, jobs: int = 1, progress: bool = True) -> list[TrialSpec]:
    """Simulate (or reuse from ``cache``) the standard scenarios for each mesh.

    Parameters
    ----------
    cache : folder of the cached trials, ``<cache>/<mesh stem>/<scenario>``
    scenarios : scenario names, default :data:`app.sim.scenarios.STANDARD`
    seconds : duration of each trial (or a mapping scenario -> duration), default each scenario's own
    meshes : mesh paths, default the project's mesh and the pelvis crest meshes found
    """
    from app.sim.scenarios import STANDARD, get_scenario
    from app.sim.simulator import DEFAULT_MESH

    scenarios = list(scenarios or STANDARD)
    for name in scenarios:
        try:
            get_scenario(name)
        except ValueError as exc:
            raise ConfigError("--scenarios", str(exc)) from None
    meshes = [Path(m) for m in meshes] if meshes else [DEFAULT_MESH, *pelvis_crest_meshes()]
    for m in meshes:
        if not m.is_file():
            raise ConfigError("--meshes", f"no such mesh file: {m}")
    specs, todo = [], []
    for mesh in meshes:
        for name in scenarios:
            duration = _seconds_for(seconds, name) or get_scenario(name).seconds
            out = Path(cache) / mesh.stem / name
            specs.append(TrialSpec(str(out), mesh.stem, name))
            if not _cache_valid(out, name, duration, seed, mesh):
                todo.append({"out": str(out), "mesh": str(mesh), "scenario": name, "seconds": duration, "seed": seed})
    if todo:
        log.info("simulating %d trials into %s", len(todo), cache)
        for _ in _map(_simulate_task, todo, jobs, desc="simulating", unit="trial", progress=progress):
            pass
    from app.trial.reader import open_trial

    for spec in specs:
        spec.frames = len(open_trial(spec.path))
    return specs


def recorded_trials(dirs, seconds: float | dict | None = None) -> list[TrialSpec]:
    """TrialSpecs of existing trial directories (each needs ``groundtruth.txt`` and ``initial_pose``)."""
    from app.errors import TrialFormatError
    from app.trial.reader import open_trial

    specs = []
    for d in dirs:
        reader = open_trial(d)
        if reader.groundtruth is None:
            raise TrialFormatError(Path(d) / "groundtruth.txt", "bench needs ground truth to score a trial (none found)")
        scenario = Path(d).name
        info = Path(d) / "simulation.yaml"
        if info.is_file():
            try:
                scenario = (yaml.safe_load(info.read_text()) or {}).get("scenario", {}).get("name", scenario)
            except yaml.YAMLError:
                pass
        n = len(reader)
        length = _seconds_for(seconds, scenario) if isinstance(seconds, dict) and scenario in seconds \
            else _seconds_for(seconds)
        if length:
            n = int(np.searchsorted(reader.stamps, reader.stamps[0] + length, side="left"))
        specs.append(TrialSpec(str(d), Path(reader.meta.mesh).stem, scenario, frames=n,
                               max_frames=n if n < len(reader) else None))
    names = [s.name for s in specs]
    for spec in specs:   # two trials of one mesh and scenario: name them by their folder
        if names.count(spec.name) > 1:
            spec.scenario = f"{spec.scenario}@{Path(spec.path).name}"
    return specs


# --------------------------------------------------------------------------- one run

def static_pairs(T_gt: np.ndarray, stamps: np.ndarray, settle_s: float = JITTER_SETTLE_S) -> np.ndarray:
    """(N,) bool: frame k and k-1 have equal ground-truth poses and k is past the settling time."""
    from app.geometry import se3

    T_gt = np.asarray(T_gt)
    mask = np.zeros(len(T_gt), dtype=bool)
    if len(T_gt) < 2:
        return mask
    moved_t = np.linalg.norm(T_gt[1:, :3, 3] - T_gt[:-1, :3, 3], axis=1)
    moved_r = np.asarray(se3.rotation_angle(T_gt[1:], T_gt[:-1]))
    mask[1:] = (moved_t < STATIC_TRANSLATION_M) & (moved_r < STATIC_ROTATION_RAD)
    mask &= np.asarray(stamps) - stamps[0] >= settle_s
    return mask


def jitter(T_est: np.ndarray, pairs: np.ndarray) -> dict:
    """RMS frame-to-frame change of the estimate over ``pairs`` (frames k with k-1): mm and deg."""
    from app.geometry import se3

    idx = np.nonzero(pairs)[0]
    idx = idx[idx >= 1]
    if len(idx) == 0:
        return {"translation_mm": float("nan"), "rotation_deg": float("nan"), "pairs": 0}
    dt = np.linalg.norm(T_est[idx, :3, 3] - T_est[idx - 1, :3, 3], axis=1)
    dr = np.asarray(se3.rotation_angle(T_est[idx], T_est[idx - 1]))
    return {"translation_mm": float(1e3 * np.sqrt(np.mean(dt ** 2))),
            "rotation_deg": float(np.rad2deg(np.sqrt(np.mean(dr ** 2)))), "pairs": int(len(idx))}


def vsd_series(trial_dir: str | Path, T_est: np.ndarray, n: int, resolution=VSD_RESOLUTION) -> np.ndarray:
    """e_VSD of the first ``n`` frames: the trial's mesh rendered at the estimate and the truth."""
    from app import metrics
    from app.depth_image import downsample_nearest
    from app.geometry import se3
    from app.render.context import shared_context
    from app.render.scene import SceneRenderer
    from app.trial.reader import open_trial

    reader = open_trial(trial_dir)
    camera = reader.meta.camera.resized(*resolution)
    mesh = reader.load_mesh()
    T_base_camera, valid = reader.camera_poses()
    renderer = SceneRenderer(shared_context(), camera)
    renderer.add_mesh("bone", np.asarray(mesh.vertices), np.asarray(mesh.faces), 1)
    out = np.full(n, np.nan)
    try:
        for i in range(n):
            if not valid[i]:
                continue
            T_camera_base = se3.inverse(T_base_camera[i])
            d_est, _ = renderer.render({"bone": T_camera_base @ T_est[i]})
            d_gt, _ = renderer.render({"bone": T_camera_base @ reader.groundtruth[i]})
            measured = downsample_nearest(reader.read_depth(i), *resolution)
            out[i] = metrics.vsd(d_est, d_gt, measured, K=camera.K)
    finally:
        renderer.release()
    return out


def run_one(config: BenchConfig, trial: TrialSpec, out_dir: str | Path | None = None, progress=None,
            with_vsd: bool = True) -> dict:
    """Replay ``trial`` with ``config`` and score it; a JSON-ready row (module docstring's columns)."""
    from app import metrics
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.trial.reader import open_trial

    make_tracker, tracker_config = None, config.tracker
    if config.kind == "icp":
        from app.baselines.icp import ICPTracker

        params = config.icp
        make_tracker = lambda mesh, camera: ICPTracker(params, mesh, camera)  # noqa: E731
        tracker_config = load_config(None)
    t0 = time.perf_counter()
    result = replay(trial.path, out_dir, tracker_config, rrd=False, progress=progress,
                    max_frames=trial.max_frames, make_tracker=make_tracker)
    wall = time.perf_counter() - t0
    reader = open_trial(trial.path)
    n = len(result.stamps)
    T_gt = np.asarray(reader.groundtruth[:n])
    T_est = result.T_base_bone
    points = np.asarray(reader.load_mesh().vertices)
    add_s, mdd_s = metrics.symmetric_errors(T_est, T_gt, points)
    add_mm = result.errors["add_mm"]
    statuses = np.array(result.statuses)
    ok = statuses == "ok"
    vsd = vsd_series(trial.path, T_est, n) if with_vsd else np.full(n, np.nan)
    t_rel = result.stamps - result.stamps[0]
    row = {
        "config": config.name, "config_description": config.describe(), "config_source": config.source,
        "tracker": config.kind, "trial": trial.name, "trial_path": trial.path, "mesh": trial.mesh,
        "scenario": trial.scenario, "frames": n,
        "fps": result.summary["processing_rate_hz"], "wall_s": wall, "gl": result.summary.get("gl"),
        "timings_ms": result.summary.get("timings_ms", {}),
        "add_mm": metrics.summarise(add_mm), "add_s_mm": metrics.summarise(1e3 * add_s),
        "mdd_s_mm": metrics.summarise(1e3 * mdd_s), "translation_mm": metrics.summarise(result.errors["trans_mm"]),
        "rotation_deg": metrics.summarise(result.errors["rot_deg"]),
        "vsd": metrics.summarise(vsd), "vsd_recall": metrics.vsd_recall(vsd[np.isfinite(vsd)]) if with_vsd else float("nan"),
        "lost_pct": float(100 * np.mean(add_mm > LOST_ADD_MM)),
        "status_pct": {s: float(100 * np.mean(statuses == s)) for s in ("ok", "uncertain", "lost")},
        "dangerous_frames": int(np.sum(ok & (add_mm > DANGEROUS_ADD_MM))),
        "jitter": jitter(T_est, static_pairs(T_gt, result.stamps)),
        "series": {"t": t_rel.round(4).tolist(), "add_mm": np.round(add_mm, 4).tolist(),
                   "rot_deg": np.round(result.errors["rot_deg"], 4).tolist(),
                   "vsd": [None if not np.isfinite(v) else round(float(v), 4) for v in vsd],
                   "status": result.statuses},
    }
    return row


def _run_task(task: dict) -> dict:
    """Worker entry point (spawned process: its own GL context)."""
    logging.basicConfig(level=logging.WARNING)
    return run_one(task["config"], task["trial"], task.get("out_dir"), with_vsd=task.get("with_vsd", True))


def _map(fn, tasks: list, jobs: int, desc: str, unit: str, progress: bool = True, weights=None):
    """Yield fn(task) for each task (in completion order when parallel) with a tqdm bar."""
    from tqdm import tqdm

    weights = weights or [1] * len(tasks)
    with tqdm(total=sum(weights), desc=desc, unit=unit, disable=not progress, dynamic_ncols=True) as bar:
        if jobs <= 1 or len(tasks) <= 1:
            for task, w in zip(tasks, weights):
                yield fn(task)
                bar.update(w)
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(fn, task): w for task, w in zip(tasks, weights)}
            for future in as_completed(futures):
                yield future.result()
                bar.update(futures[future])


def run_bench(configs: list[BenchConfig], trials: list[TrialSpec], jobs: int = 1, out_dir: str | Path | None = None,
              with_vsd: bool = True, progress: bool = True) -> list[dict]:
    """Every configuration on every trial; rows ordered by trial, then configuration.

    With ``jobs`` > 1 the runs go to a spawned process pool (each process opens its own GL
    context); frames/s then measure a shared CPU. ``out_dir`` keeps each run's estimate.txt and
    status.csv under ``<out_dir>/<config>/<mesh>/<scenario>``.
    """
    tasks = []
    for trial in trials:
        for config in configs:
            task_out = str(Path(out_dir) / config.name / trial.mesh / trial.scenario) if out_dir else None
            tasks.append({"config": config, "trial": trial, "out_dir": task_out, "with_vsd": with_vsd})
    weights = [max(t["trial"].max_frames or t["trial"].frames, 1) for t in tasks]
    if jobs <= 1:
        rows = _run_serial(tasks, weights, progress)
    else:
        rows = list(_map(_run_task, tasks, jobs, desc="bench", unit="frame", progress=progress, weights=weights))
    order = {(t["trial"].name, t["config"].name): k for k, t in enumerate(tasks)}
    return sorted(rows, key=lambda r: order[(r["trial"], r["config"])])


def _run_serial(tasks, weights, progress: bool) -> list[dict]:
    from tqdm import tqdm

    rows = []
    with tqdm(total=sum(weights), desc="bench", unit="frame", disable=not progress, dynamic_ncols=True) as bar:
        for task, w in zip(tasks, weights):
            bar.set_postfix_str(f"{task['config'].name} on {task['trial'].name}")
            done = [0]

            def step(i, total, done=done):
                bar.update(i - done[0])
                done[0] = i

            rows.append(run_one(task["config"], task["trial"], task["out_dir"], progress=step, with_vsd=task["with_vsd"]))
            bar.update(w - done[0])
    return rows


# --------------------------------------------------------------------------- outputs

COLUMNS = ("config", "scenario", "fps", "ADD med", "ADD p95", "rot med", "rot p95", "VSD rec",
           "lost %", "ok %", "danger", "jit mm", "jit deg")


def _row_cells(r: dict) -> list[str]:
    def f(x, digits=2):
        return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"

    return [r["config"], r["trial"], f(r["fps"], 1), f(r["add_mm"]["median"]), f(r["add_mm"]["p95"]),
            f(r["rotation_deg"]["median"]), f(r["rotation_deg"]["p95"]), f(r["vsd_recall"]),
            f(r["lost_pct"], 1), f(r["status_pct"]["ok"], 1), str(r["dangerous_frames"]),
            f(r["jitter"]["translation_mm"], 3), f(r["jitter"]["rotation_deg"], 3)]


def table(rows: list[dict], markdown: bool = False) -> str:
    """The results table: one row per configuration x trial (ADD mm, rotation deg)."""
    cells = [_row_cells(r) for r in rows]
    header = list(COLUMNS)
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(c) + " |" for c in cells]
        return "\n".join(lines)
    widths = [max(len(h), *(len(c[i]) for c in cells)) if cells else len(h) for i, h in enumerate(header)]
    fmt = lambda cs: "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(cs, widths)))  # noqa: E731
    lines = [fmt(header), "-" * len(fmt(header))]
    previous = None
    for r, c in zip(rows, cells):
        if previous is not None and r["trial"] != previous:
            lines.append("")
        previous = r["trial"]
        lines.append(fmt(c))
    return "\n".join(lines)


def write_json(rows: list[dict], path: str | Path, meta: dict | None = None) -> None:
    """The rows (with per-frame series) and run information as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return x

    path.write_text(json.dumps(clean({"meta": meta or {}, "columns": {
        "fps": "processed frames per second of the replay loop (wall time) on this machine",
        "add_mm": "ADD, mm", "rotation_deg": "rotation error, deg", "vsd_recall": "fraction of frames with e_VSD < 0.3 (tau 20 mm)",
        "lost_pct": f"% frames with ADD > {LOST_ADD_MM} mm", "dangerous_frames": f"frames with status ok and ADD > {DANGEROUS_ADD_MM} mm",
        "jitter": "RMS frame-to-frame change of the estimate while the ground truth is static (after settling)",
    }, "rows": rows}), indent=1))


def plot(rows: list[dict], folder: str | Path) -> list[Path]:
    """PNGs: ADD over time per configuration for each trial, and frames/s per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    configs = list(dict.fromkeys(r["config"] for r in rows))
    colours = {c: plt.get_cmap("tab10")(k % 10) for k, c in enumerate(configs)}
    for trial in dict.fromkeys(r["trial"] for r in rows):
        fig, (ax_add, ax_rot) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for r in (r for r in rows if r["trial"] == trial):
            s = r["series"]
            ax_add.plot(s["t"], s["add_mm"], label=r["config"], color=colours[r["config"]], lw=1)
            danger = [(t, a) for t, a, st in zip(s["t"], s["add_mm"], s["status"]) if st == "ok" and a > DANGEROUS_ADD_MM]
            if danger:
                ax_add.plot(*zip(*danger), "x", color=colours[r["config"]], ms=5)
            ax_rot.plot(s["t"], s["rot_deg"], color=colours[r["config"]], lw=1)
        ax_add.axhline(DANGEROUS_ADD_MM, color="grey", ls="--", lw=0.8)   # x: status ok above this line
        ax_add.set_yscale("log")
        ax_add.set_ylabel("ADD (mm)")
        ax_rot.set_yscale("log")
        ax_rot.set_ylabel("rotation error (deg)")
        ax_rot.set_xlabel("time (s)")
        ax_add.set_title(f"error over time: {trial}")
        ax_add.legend(fontsize=8, ncol=3)
        fig.tight_layout()
        path = folder / f"error_{trial.replace('/', '__')}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(configs)), 4))
    fps = [[r["fps"] for r in rows if r["config"] == c] for c in configs]
    ax.bar(range(len(configs)), [np.mean(v) for v in fps], color=[colours[c] for c in configs])
    for k, v in enumerate(fps):
        ax.plot([k] * len(v), v, "k.", ms=4)
    ax.set_xticks(range(len(configs)), configs, rotation=20, ha="right")
    ax.set_ylabel("frames / s (mean over trials; dots: each trial)")
    ax.set_title("processing rate per configuration")
    fig.tight_layout()
    path = folder / "rate.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    written.append(path)
    return written
