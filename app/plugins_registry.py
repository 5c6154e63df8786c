"""Plugins by kind and name, found through the entry-point group ``osteonav.plugins``.

An entry point is named ``<kind>.<name>`` (kind one of camera, robot, tracker, output) and points
to a class (or factory) called with the plugin's ``params`` mapping as keyword arguments::

    [project.entry-points."osteonav.plugins"]
    "camera.realsense" = "plugins.realsense:RealSenseCamera"

A third-party package adds its own the same way. ``app`` never imports ``plugins`` directly: it
loads what the entry points name (and :func:`register` adds plugins at run time, e.g. in tests).
An unknown name raises :class:`~app.errors.ConfigError` naming the key and the names available.
"""
from __future__ import annotations

import importlib
import inspect
import logging
from importlib.metadata import entry_points
from typing import Any, Callable

from app.errors import ConfigError
from app.interfaces import KINDS

log = logging.getLogger(__name__)

GROUP = "osteonav.plugins"

# The built-in plugins, also declared as entry points in pyproject.toml; listed here too so that a
# source checkout that was never pip-installed still finds them.
BUILTIN: dict[str, str] = {
    "camera.simulated": "plugins.trial_player:SimulatedCamera",
    "camera.recorded": "plugins.trial_player:RecordedCamera",
    "camera.realsense": "plugins.realsense:RealSenseCamera",
    "robot.simulated": "plugins.trial_player:SimulatedRobot",
    "robot.recorded": "plugins.trial_player:RecordedRobot",
    "robot.static": "plugins.static_robot:StaticRobot",
    "camera.marker_simulated": "plugins.marker_camera:MarkerSimulatedCamera",
    "robot.ur": "plugins.ur:URRobot",
    "tracker.particle_filter": "plugins.tracker_pf:ParticleFilterTracker",
    "tracker.marker_imu": "plugins.marker_imu:MarkerImuTracker",
    "tracker.icp": "plugins.tracker_icp:ICPTrackerPlugin",
    "output.rerun": "plugins.rerun_output:RerunOutput",
    "output.recorder": "plugins.recorder:Recorder",
    "output.projector": "plugins.projector_output:ProjectorOutput",
}

_runtime: dict[str, Callable[..., Any]] = {}


def register(kind: str, name: str, factory: Callable[..., Any]) -> None:
    """Add (or replace) a plugin at run time."""
    _check_kind(kind)
    _runtime[f"{kind}.{name}"] = factory


def unregister(kind: str, name: str) -> None:
    _runtime.pop(f"{kind}.{name}", None)


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ConfigError("plugin kind", f"unknown kind {kind!r}; allowed: {', '.join(KINDS)}")


def _entry_points() -> dict[str, str]:
    found = {}
    for ep in entry_points(group=GROUP):
        found[ep.name] = ep.value
    return found


def available(kind: str) -> list[str]:
    """Names of the plugins of ``kind``, sorted."""
    _check_kind(kind)
    keys = set(BUILTIN) | set(_entry_points()) | set(_runtime)
    return sorted(k.split(".", 1)[1] for k in keys if k.startswith(kind + "."))


def load(kind: str, name: str, key: str | None = None) -> Callable[..., Any]:
    """The class or factory of plugin ``kind.name``; ``key`` is the config key for error messages."""
    _check_kind(kind)
    full = f"{kind}.{name}"
    key = key or f"{kind}.plugin"
    if full in _runtime:
        return _runtime[full]
    target = _entry_points().get(full) or BUILTIN.get(full)
    if target is None:
        raise ConfigError(key, f"unknown {kind} plugin {name!r}; allowed: {', '.join(available(kind))}")
    module_name, _, attr = target.partition(":")
    module = importlib.import_module(module_name)
    obj = module
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def create(kind: str, name: str, params: dict | None, key: str | None = None, **context: Any) -> Any:
    """Instantiate plugin ``kind.name`` with ``params``; unknown or missing parameters are named.

    ``context`` holds what the session passes besides the file's parameters (a tracker gets
    ``mesh``, ``camera`` and ``T_flange_camera``); it is not checked against the file's keys.
    """
    factory = load(kind, name, key)
    params = dict(params or {})
    key = key or kind
    try:
        sig = inspect.signature(factory)
    except (TypeError, ValueError):
        sig = None
    if sig is not None and not any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values()):
        allowed = [n for n, p in sig.parameters.items()
                   if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and n not in context]
        for k in params:
            if k not in allowed:
                raise ConfigError(f"{key}.params.{k}", f"unknown parameter of {kind} plugin {name!r}; "
                                                       f"allowed: {', '.join(allowed) or '(none)'}")
        for n, p in sig.parameters.items():
            if (p.default is p.empty and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
                    and n not in params and n not in context):
                raise ConfigError(f"{key}.params.{n}", f"required parameter of {kind} plugin {name!r} is missing")
    return factory(**context, **params)
