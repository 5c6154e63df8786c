"""Bench trials: the standard scenarios simulated per mesh and sensor model (cached), or recorded trial directories."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from app.bench.configs import REPO
from app.bench.parallel import pmap
from app.errors import ConfigError

log = logging.getLogger("app.bench.bench")

PELVIS_DIR = REPO.parent / "shared" / "data" / "pelvis"
DEFAULT_CACHE = Path("recordings") / "bench"
_DEFAULT_SENSOR_DICT = {"model": "independent", "k": 0.0015, "sigma_base": 0.0003, "z_min": 0.28, "z_max": 3.0,
                        "edge_jump": 0.006, "edge_dilation": 1}   # what the simulator used before sensors were named
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


@dataclass
class TrialSpec:
    """A trial to run: its directory and how to name it in the table."""

    path: str
    mesh: str
    scenario: str
    frames: int = 0
    max_frames: int | None = None
    seed: int = 0
    simulation: dict | None = None   # set by standard_trials(lazy=True): simulated just before its first run
    sensor: str = "independent"      # the depth sensor model's label (app.sim.sensors.sensor_label)

    @property
    def name(self) -> str:
        return f"{self.mesh}/{self.scenario}" + (f"/seed{self.seed}" if self.seed else "")

    def ensure(self) -> None:
        """Simulate the trial now if it was left for later (lazy), and count its frames."""
        if self.simulation is not None:
            from app.trial.reader import open_trial

            _simulate_task(self.simulation)
            self.simulation = None
            self.frames = len(open_trial(self.path))


def pelvis_crest_meshes(folder: Path = PELVIS_DIR) -> list[Path]:
    """The ``crest_*.ply`` meshes of the shared pelvis folder; empty (with a log line) when absent."""
    if not folder.is_dir():
        log.info("no pelvis meshes at %s: benchmarking the default mesh only", folder)
        return []
    return sorted(folder.glob("crest_*.ply"))


def _cache_valid(trial: Path, scenario: str, seconds: float, seed: int, mesh_path: Path, sensor: dict) -> bool:
    """Whether ``trial`` holds a complete simulation of these parameters (a simulation.yaml without a
    ``sensor`` entry was made by the ``independent`` model with its defaults, before sensors were named)."""
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
            and Path(info.get("mesh_source", "")).resolve() == mesh_path.resolve()
            and info.get("sensor", _DEFAULT_SENSOR_DICT) == sensor)


def _simulate_task(task: dict) -> dict:
    from app.sim.simulator import simulate

    from app.sim.sensors import sensor_from_dict

    sensor = sensor_from_dict(task["sensor"]) if task.get("sensor") else "independent"
    summary = simulate(task["out"], mesh_path=task["mesh"], scenario_name=task["scenario"], seconds=task["seconds"],
                       seed=task["seed"], overwrite=True, sensor=sensor)
    return {"out": task["out"], "frames": summary.frames}


def trial_dir(cache: str | Path, mesh: Path, scenario: str, seed: int, sensor: str = "independent") -> Path:
    """``<cache>/<mesh stem>/<scenario>`` for seed 0, ``.../<scenario>_seed<N>`` for another seed; another
    sensor model than ``independent`` (its label, :func:`app.sim.sensors.sensor_label`) adds ``@<label>``."""
    name = scenario if seed == 0 else f"{scenario}_seed{seed}"
    return Path(cache) / mesh.stem / (name if sensor == "independent" else f"{name}@{sensor}")


def parse_sensors(sensors) -> list:
    """Sensor models from names or ``NAME:KEY=VALUE,...`` texts (or models); default ``[independent]``;
    ConfigError naming ``--sensors``."""
    from app.sim.sensors import DEFAULT_SENSOR, parse_sensor

    out = []
    for item in sensors or [DEFAULT_SENSOR]:
        try:
            out.append(parse_sensor(item) if isinstance(item, str) else item)
        except ValueError as exc:
            raise ConfigError("--sensors", str(exc)) from None
    return out


def standard_trials(cache: str | Path = DEFAULT_CACHE, scenarios=None, seconds: float | dict | None = None,
                    meshes=None, seed: int = 0, jobs: int = 1, progress: bool = True, seeds=None,
                    lazy: bool = False, sensors=None) -> list[TrialSpec]:
    """Simulate (or reuse from ``cache``) the standard scenarios for each mesh (and seed, and sensor model).

    Parameters
    ----------
    cache : folder of the cached trials, :func:`trial_dir`
    scenarios : scenario names, default :data:`app.sim.scenarios.STANDARD`
    seconds : duration of each trial (or a mapping scenario -> duration), default each scenario's own
    meshes : mesh paths, default the project's mesh and the pelvis crest meshes found
    seeds : simulation seeds (default ``[seed]``); the specs are ordered seed, scenario, sensor, mesh, so
        that the first runs of a long matrix cover every scenario once
    sensors : depth sensor models (names, ``NAME:KEY=VALUE,...`` or models of :mod:`app.sim.sensors`),
        default ``['independent']``; a trial of another model is cached in ``<scenario>[_seedN]@<label>``
        and named ``<scenario>@<label>`` in the tables
    lazy : do not simulate now; each spec simulates itself on :meth:`TrialSpec.ensure` (a long
        matrix then starts running at once and a partial run leaves no unused simulations)
    """
    from app.sim.scenarios import STANDARD, get_scenario
    from app.sim.sensors import sensor_label, sensor_to_dict
    from app.sim.simulator import DEFAULT_MESH

    models = parse_sensors(sensors)
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
    for s in (seeds if seeds is not None else [seed]):
        for name in scenarios:
            duration = _seconds_for(seconds, name) or get_scenario(name).seconds
            for model in models:
                label, block = sensor_label(model), sensor_to_dict(model)
                for mesh in meshes:
                    out = trial_dir(cache, mesh, name, s, label)
                    spec = TrialSpec(str(out), mesh.stem, name if label == "independent" else f"{name}@{label}",
                                     seed=int(s), sensor=label)
                    specs.append(spec)
                    if not _cache_valid(out, name, duration, s, mesh, block):
                        task = {"out": str(out), "mesh": str(mesh), "scenario": name, "seconds": duration,
                                "seed": int(s), "sensor": block}
                        if lazy:
                            spec.simulation, spec.frames = task, int(round(duration * 90))
                        else:
                            todo.append(task)
    if todo:
        log.info("simulating %d trials into %s", len(todo), cache)
        for _ in pmap(_simulate_task, todo, jobs, desc="simulating", unit="trial", progress=progress):
            pass
    from app.trial.reader import open_trial

    for spec in specs:
        if spec.simulation is None:
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
                               max_frames=n if n < len(reader) else None, sensor=_recorded_sensor(reader.meta)))
    names = [s.name for s in specs]
    for spec in specs:   # two trials of one mesh and scenario: name them by their folder
        if names.count(spec.name) > 1:
            spec.scenario = f"{spec.scenario}@{Path(spec.path).name}"
    return specs


def _recorded_sensor(meta) -> str:
    """The label of the sensor model named in a trial's ``sensor`` block; ``unknown`` without a valid one."""
    from app.sim.sensors import sensor_from_dict, sensor_label

    try:
        return sensor_label(sensor_from_dict(meta.extra.get("sensor")))
    except ValueError:
        return "unknown"
