"""Bench configurations: the built-in YAML files of ``configs/bench/`` and the user's (see :mod:`app.bench.bench`)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from app.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
BUILTIN_DIR = REPO / "configs" / "bench"
BUILTIN_ORDER = ("osteonav_default", "A_cpu", "A_cadaver", "thesis_blockwise", "thesis_joint", "thesis_complex", "icp")
TRACKERS = ("particle_filter", "icp")
ICP_ZERO_OK = ("silhouette_px",)     # integer ICP keys that may be 0 (the others must be >= 1)


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
            low = 0 if name in ICP_ZERO_OK else 1
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ConfigError(key, f"expected an integer >= {low}, got {value!r}", source)
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(key, f"expected a number > 0, got {value!r}", source)
            if name.endswith("fitness") and value > 1:
                raise ConfigError(key, f"a fitness is a fraction in (0, 1], got {value!r}", source)
            value = float(value)
        kwargs[name] = value
    return ICPParams(**kwargs)
