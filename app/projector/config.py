"""The ``projector:`` configuration block (configs/projector.yaml) and what it builds.

Keys (all validated; a bad value raises :class:`app.errors.ConfigError` naming ``projector.KEY``)::

    projector:
      width, height, K, T_camera_projector[, dist]   # the model (app.projector.model)
      line_width_mm: 1.0        # outline width on the bone
      color: [0, 255, 0]        # outline RGB
      max_age_s: 0.2            # staleness limit of the safety gate (app.projector.view)
      plan_tolerance_mm: 2.0    # plan-to-bone distance limit (app.projector.plan)
      plan: {file: PATH}        # YAML polylines or a transplant mesh, bone frame; relative to the YAML
      plan: {shape: box|hockey, center_x_mm, length_mm, width_mm, angle_deg}   # generated on the crest

Usage::

    cfg = load_projector_config("configs/projector.yaml")
    plan = build_plan(cfg, vertices, faces)
    view = ProjectorView.create(cfg.projector, vertices, faces, plan, line_width=cfg.line_width_m,
                                color=cfg.color, max_age_s=cfg.max_age_s)
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.errors import ConfigError
from app.projector.model import ProjectorModel, default_projector
from app.errors import MeshError
from app.projector.plan import PLAN_TOLERANCE_M, SHAPES, Plan, derive_crest_plan, load_plan, make_crest_plan

log = logging.getLogger(__name__)

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "projector.yaml"
_KEYS = {"width", "height", "K", "T_camera_projector", "dist", "line_width_mm", "color", "max_age_s",
         "plan_tolerance_mm", "plan"}


@dataclass
class ProjectorConfig:
    projector: ProjectorModel = field(default_factory=default_projector)
    line_width_m: float = 0.001
    color: tuple = (0, 255, 0)
    max_age_s: float = 0.2
    plan_tolerance_m: float = PLAN_TOLERANCE_M
    plan: dict = field(default_factory=lambda: {"shape": "box", "center_x_mm": -20.0})
    base_dir: Path = field(default_factory=Path.cwd)
    source: str | None = None


def _positive(d: dict, key: str, default: float, source) -> float:
    value = d.get(key, default)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"projector.{key}", f"expected a number, got {value!r}", source) from None
    if not np.isfinite(value) or value <= 0:
        raise ConfigError(f"projector.{key}", f"must be > 0, got {value}", source)
    return value


def parse_projector_config(data: dict, source: str | None = None, base_dir: Path | None = None) -> ProjectorConfig:
    """A ProjectorConfig from the mapping under ``projector:`` (or a whole file's mapping holding it)."""
    if isinstance(data, dict) and "projector" in data and isinstance(data["projector"], dict):
        data = data["projector"]
    if not isinstance(data, dict):
        raise ConfigError("projector", f"expected a mapping, got {type(data).__name__}", source)
    unknown = sorted(set(data) - _KEYS)
    if unknown:
        raise ConfigError(f"projector.{unknown[0]}", f"unknown key; valid: {', '.join(sorted(_KEYS))}", source)
    model = ProjectorModel.from_dict(data, source) if "K" in data or "T_camera_projector" in data else default_projector()
    color = data.get("color", [0, 255, 0])
    if (not isinstance(color, (list, tuple)) or len(color) != 3
            or not all(isinstance(c, (int, float)) and 0 <= c <= 255 for c in color)):
        raise ConfigError("projector.color", f"expected [r, g, b] in 0..255, got {color!r}", source)
    plan = data.get("plan", {"shape": "box", "center_x_mm": -20.0})
    if not isinstance(plan, dict) or ("file" in plan) == ("shape" in plan):
        raise ConfigError("projector.plan", "expected {file: PATH} or {shape: box|hockey, ...}", source)
    return ProjectorConfig(
        projector=model,
        line_width_m=_positive(data, "line_width_mm", 1.0, source) / 1000.0,
        color=tuple(int(c) for c in color),
        max_age_s=_positive(data, "max_age_s", 0.2, source),
        plan_tolerance_m=_positive(data, "plan_tolerance_mm", PLAN_TOLERANCE_M * 1000, source) / 1000.0,
        plan=dict(plan), base_dir=base_dir or Path.cwd(), source=source)


def load_projector_config(path: "str | Path" = DEFAULT_CONFIG) -> ProjectorConfig:
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError("projector", f"configuration file {path} does not exist")
    return parse_projector_config(yaml.safe_load(path.read_text()) or {}, str(path), path.resolve().parent)


def build_plan(cfg: ProjectorConfig, vertices: np.ndarray, faces: np.ndarray, derive: bool = False,
               quiet: bool = False) -> Plan:
    """The configured plan, checked against the bone mesh (MeshError when it is not on it).

    ``derive`` (replay of a recorded trial): when the configured plan does not fit this mesh, one
    warning line and a plan of the configured shape and size placed on this mesh's ridge instead
    (:func:`app.projector.plan.derive_crest_plan`; its ``name`` says so). ``quiet``: no warning line
    (a benchmark scoring many meshes, whose table names the plan).
    """
    try:
        return _configured_plan(cfg, vertices, faces)
    except MeshError as exc:
        if not derive:
            raise
        shape = cfg.plan.get("shape", "box")
        sizes = {k: float(cfg.plan.get(k, d)) for k, d in (("length_mm", 20.0), ("width_mm", 10.0), ("angle_deg", 0.0))}
        plan = derive_crest_plan(shape if shape in SHAPES else "box", vertices, faces, sizes["length_mm"] / 1000.0,
                                 sizes["width_mm"] / 1000.0, sizes["angle_deg"])
        if not quiet:
            log.warning("projector: the configured plan does not fit this mesh (%s); using a %s", exc, plan.name)
        return plan


def _configured_plan(cfg: ProjectorConfig, vertices: np.ndarray, faces: np.ndarray) -> Plan:
    p = cfg.plan
    if "file" in p:
        path = Path(p["file"])
        if not path.is_absolute():
            # relative to the YAML file, else to the working directory (repo-relative paths like plans/x.yaml)
            path = cfg.base_dir / path if (cfg.base_dir / path).exists() else path
        return load_plan(path, vertices, faces, tolerance=cfg.plan_tolerance_m)
    shape = p["shape"]
    if shape not in SHAPES:
        raise ConfigError("projector.plan.shape", f"unknown shape {shape!r}; valid: {', '.join(SHAPES)}", cfg.source)
    unknown = sorted(set(p) - {"shape", "center_x_mm", "length_mm", "width_mm", "angle_deg"})
    if unknown:
        raise ConfigError(f"projector.plan.{unknown[0]}", "unknown key; valid: shape, center_x_mm, length_mm, "
                          "width_mm, angle_deg", cfg.source)
    try:
        sizes = {k: float(p.get(k, d)) for k, d in
                 (("center_x_mm", 0.0), ("length_mm", 20.0), ("width_mm", 10.0), ("angle_deg", 0.0))}
    except (TypeError, ValueError) as exc:
        raise ConfigError("projector.plan", f"sizes must be numbers ({exc})", cfg.source) from None
    return make_crest_plan(shape, vertices, faces, center_x=sizes["center_x_mm"] / 1000.0,
                           length=sizes["length_mm"] / 1000.0, width=sizes["width_mm"] / 1000.0,
                           angle_deg=sizes["angle_deg"])
