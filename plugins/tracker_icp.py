"""The Open3D point-to-plane ICP baseline as a session plugin (``tracker: icp``).

The :class:`app.pipeline.engine_tracker.EngineTracker` of :class:`app.baselines.icp.ICPTracker`, the tracker ``osteonav bench`` compares
the particle filter with. ``params.config`` names an ICP YAML (``tracker: icp`` plus an ``icp``
section, e.g. ``configs/bench/icp.yaml``; relative to the session file); ``params.icp`` overrides
single keys inline; neither: the bench's built-in ``icp`` configuration. Every key is checked by
:func:`app.bench.configs.load_icp_params` (an unknown or wrong one is named with the fix).

ICP has no particles and no uncertainty model: its status is ok while its fitness and inlier RMSE
are good, which does not catch a confident wrong fit (BENCHMARKS.md §2). For comparison in a live
session, not for projecting a template in the operating room.
"""
from __future__ import annotations

from pathlib import Path

from app.pipeline.engine_tracker import EngineTracker


class ICPTrackerPlugin(EngineTracker):
    kind, name = "tracker", "icp"

    def __init__(self, mesh, camera, T_flange_camera=None, config: str | None = None, icp: dict | None = None):
        from app.baselines.icp import ICPTracker

        engine = ICPTracker(_params(config, icp), mesh, camera)
        engine.T_flange_camera = T_flange_camera
        super().__init__(engine)


def _params(config: str | None, overrides: dict | None):
    """ICPParams from the YAML ``config`` (or the built-in bench configuration) with ``overrides``."""
    import dataclasses

    import yaml

    from app.bench.configs import load_icp_params, resolve_configs
    from app.errors import ConfigError

    if config is None:
        base = dataclasses.asdict(resolve_configs(["icp"])[0].icp)
        source = "the built-in icp configuration"
    else:
        path = Path(config)
        if not path.is_file():
            raise ConfigError("tracker.params.config", f"file not found: {path}")
        data = yaml.safe_load(path.read_text()) or {}
        if not isinstance(data, dict):
            raise ConfigError("tracker.params.config", f"{path}: expected a mapping with an 'icp' section")
        data.pop("tracker", None)
        base = dataclasses.asdict(load_icp_params(data, str(path)))
        source = str(path)
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError("tracker.params.icp", f"expected a mapping of ICP keys, got {overrides!r}")
    merged = {**base, **(overrides or {})}
    merged["resolution"] = list(merged["resolution"])
    return load_icp_params({"icp": merged}, f"{source} + tracker.params.icp")
