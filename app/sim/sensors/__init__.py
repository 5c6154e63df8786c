"""Depth sensor models of the simulator, by name: ``independent`` (the default), ``stereo``, ``tof``.

A model is a frozen dataclass with a class attribute ``name`` and
``measure(depth, rng, *, camera, depth_scale_mm, errors, bone_mask) -> (H, W) float32 metres``
(0 = invalid) from the exact rendered depth (0 = empty); each module's docstring gives its
equations and where its numbers come from. The scenario's own errors
(:class:`~app.sim.sensors.common.SceneErrors`) are applied by every model alike.

A trial names its model in trial.yaml as ``sensor: {model: NAME, <parameter>: <value>, ...}``
(:func:`sensor_to_dict`, :func:`sensor_from_dict`); on the command line a model is
``NAME`` or ``NAME:KEY=VALUE,KEY=VALUE`` (:func:`parse_sensor`), e.g. ``stereo:window_px=9``.
"""
from __future__ import annotations

from dataclasses import asdict, fields

from app.sim.sensors.common import SceneErrors
from app.sim.sensors.independent import IndependentSensor
from app.sim.sensors.stereo import StereoSensor
from app.sim.sensors.tof import TofSensor

SENSORS = {cls.name: cls for cls in (IndependentSensor, StereoSensor, TofSensor)}
DEFAULT_SENSOR = IndependentSensor.name

__all__ = ["SENSORS", "DEFAULT_SENSOR", "SceneErrors", "get_sensor", "parse_sensor", "sensor_to_dict",
           "sensor_from_dict", "sensor_label"]


def get_sensor(name: str, **params):
    """The model ``name`` with ``params`` replacing its defaults; ValueError listing the valid names/keys."""
    if name not in SENSORS:
        raise ValueError(f"unknown sensor model '{name}'; valid: {', '.join(SENSORS)}")
    cls = SENSORS[name]
    known = [f.name for f in fields(cls)]
    unknown = [k for k in params if k not in known]
    if unknown:
        raise ValueError(f"sensor model '{name}' has no parameter {', '.join(repr(k) for k in unknown)}; "
                         f"valid: {', '.join(known)}")
    types = {f.name: f.default for f in fields(cls)}
    return cls(**{k: _like(types[k], v, name, k) for k, v in params.items()})


def parse_sensor(text: str):
    """``NAME`` or ``NAME:KEY=VALUE,KEY=VALUE`` -> a model; ValueError naming the fix."""
    name, _, rest = str(text).strip().partition(":")
    params = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"sensor '{text}': expected NAME or NAME:KEY=VALUE,KEY=VALUE (e.g. stereo:window_px=9), "
                             f"got '{item}'")
        params[key.strip()] = value.strip()
    return get_sensor(name.strip(), **params)


def sensor_to_dict(sensor) -> dict:
    """trial.yaml's ``sensor`` block: ``{'model': name, **every parameter}``."""
    return {"model": sensor.name, **asdict(sensor)}


def sensor_from_dict(block) -> object:
    """The model of a trial.yaml ``sensor`` block (``{'model': NAME, ...}``); ValueError naming the fix."""
    if not isinstance(block, dict) or "model" not in block:
        raise ValueError(f"sensor: expected a mapping with 'model' (one of {', '.join(SENSORS)}), got {block!r}")
    params = {k: v for k, v in block.items() if k != "model"}
    return get_sensor(block["model"], **params)


def sensor_label(sensor) -> str:
    """A short name for file names and tables: ``NAME`` with default parameters, else ``NAME-<8 hex>``."""
    import hashlib

    default = SENSORS[sensor.name]()
    if sensor == default:
        return sensor.name
    changed = {k: v for k, v in asdict(sensor).items() if v != getattr(default, k)}
    return f"{sensor.name}-{hashlib.sha1(repr(sorted(changed.items())).encode()).hexdigest()[:8]}"


def _like(default, value, name: str, key: str):
    """``value`` converted to the type of the parameter's ``default`` (from text or YAML)."""
    if isinstance(value, str):
        text = value.strip()
        if text.lower() in ("none", "null"):
            value = None
        elif isinstance(default, bool):
            if text.lower() not in ("true", "false"):
                raise ValueError(f"sensor model '{name}': {key} expects true or false, got '{value}'")
            value = text.lower() == "true"
        else:
            try:
                value = float(text)
            except ValueError:
                raise ValueError(f"sensor model '{name}': {key} expects a number, got '{value}'") from None
    if value is None:
        return None
    if isinstance(default, bool):
        return bool(value)
    if isinstance(default, int) and float(value) == int(value):
        return int(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise ValueError(f"sensor model '{name}': {key} expects a number, got {value!r}")
