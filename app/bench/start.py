"""Start from a point on the CT crests (issue 33): found within 1 mm, its work and CPU, and safety.

Import as ``from app.bench.start import run_start``; the command is ``osteonav bench-init``. For
each crest x scenario x view x seed: a short trial is simulated (app/sim; ``static_clear``, and for
other viewpoints ``static_other_side``, the bone turned 180 deg about its crest-up axis, and
``static_far``, 0.65 m away; the view is the simulator's seed: the bone's ~8 deg tilt and the
tissue, the camera's path being the same), made point-only
(app/sim/point_start.py: no ``initial_pose``, the ``point_prior`` moved ``off`` metres off the
crest's top, 2-5 mm in a uniform direction, drawn per crest, view and seed) and replayed with the product's default configuration
(``init.method: auto``: the detector from the point). Per run:

- ``found_1mm``: the first tracked frame (the frame the detector found the bone on) lies within
  1 mm ADD of the truth;
- ``attempts``, ``evaluations``, ``refinements``: the detector's work until it found the bone (its
  attempts that found nothing included); ``cpu_s``: the process CPU seconds those attempts took, as
  measured (2 cores, shared: a loaded machine reads slower; the work counts do not change);
- ``ok_off_2mm``: frames ok while ADD > 2 mm (must be 0), ``first_ok_s``: seconds from the trial's
  start to the first ok frame (the confirmation takes ``recovery.confirm_frames`` weighed frames).
"""
from __future__ import annotations

import os
import shutil
import zlib
from pathlib import Path

import numpy as np

FOUND_MM = 1.0
SAFE_MM = 2.0


def simulate_point_trial(out: Path, mesh: Path, view: int, seed: int, seconds: float,
                         off_range_m: tuple[float, float], keep_point: bool = True,
                         scenario: str = "static_clear", sensor: str | None = None) -> float:
    """The crest's ``scenario`` trial of this view (cached under ``out``'s parent by crest, scenario,
    view and ``sensor``: the simulator's depth model, app/sim/sensors/, None its default), copied to ``out`` and made point-only with a point ``off`` m off (drawn from ``off_range_m``
    by ``seed``), or with no point either (``keep_point`` False: the whole image); returns ``off``."""
    from app.sim.point_start import make_point_only
    from app.sim.simulator import simulate

    from app.sim.sensors import DEFAULT_SENSOR

    sensor = sensor or DEFAULT_SENSOR
    tag = ("" if scenario == "static_clear" else f"_{scenario}") + ("" if sensor == DEFAULT_SENSOR else f"_{sensor}")
    cached = out.parent / f"{mesh.stem}{tag}_view{view}_{seconds:g}s"
    if not (cached / "trial.yaml").exists():
        simulate(cached, mesh_path=mesh, scenario_name=scenario, seconds=seconds, seed=view, overwrite=True,
                 sensor=sensor)
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(cached, out, copy_function=_link_frames)
    rng = np.random.default_rng([seed, view, 33, zlib.crc32(mesh.stem.encode())])
    off = float(rng.uniform(*off_range_m))
    make_point_only(out, off, rng, keep_point)
    return off


def _link_frames(src: str, dst: str) -> None:
    """Copy a cached trial's file for one start: trial.yaml copied (the start rewrites it), every other
    file hard-linked (read only by the replay; hundreds of starts each copying a trial's frames filled
    a 250 GB disk), copied where the file system cannot link."""
    from app.trial.meta import META_FILE

    if Path(src).name != META_FILE:
        try:
            os.link(src, dst)
            return
        except OSError:
            pass
    shutil.copy2(src, dst)


def run_start(trial: Path, config=None, max_frames: int | None = None) -> dict:
    """Replay the point-only ``trial`` with ``config`` (the defaults) and measure the start (module docstring)."""
    from app.config import load_config
    from app.pipeline.replay import replay

    result = replay(trial, None, config or load_config(None), rrd=False, projector=False, max_frames=max_frames)
    add = np.asarray(result.errors["add_mm"])
    statuses = np.asarray(result.statuses)
    stamps = np.asarray(result.stamps)
    start = result.summary.get("start") or {}
    found = bool(start.get("found"))
    i_found = int(np.searchsorted(stamps, start["found_stamp"])) if found else None
    ok = statuses == "ok"
    return {"frames": int(len(add)), "found": found,
            "found_1mm": bool(found and add[i_found] < FOUND_MM),
            "add_found_mm": float(add[i_found]) if found else None,
            "found_after_s": float(start["found_stamp"] - stamps[0]) if found else None,
            "attempts": int(start.get("attempts", 0)), "evaluations": int(start.get("evaluations", 0)),
            "refinements": int(start.get("refinements", 0)), "cpu_s": float(start.get("cpu_s", 0.0)),
            "wall_s": float(start.get("wall_s", 0.0)),
            "ok_off_2mm": int(np.sum(ok & (add > SAFE_MM))),
            "first_ok_s": float(stamps[np.argmax(ok)] - stamps[0]) if ok.any() else None,
            "ok_share": float(ok.mean()) if len(ok) else 0.0,
            "add_median_mm": float(np.median(add)) if len(add) else None}


def per_crest(rows: list[dict]) -> list[dict]:
    """Per crest: runs, found within 1 mm (count, share), CPU seconds to it (median, max), work
    (median evaluations, refinements), frames ok while > 2 mm off (total), first ok (median s)."""
    out = []
    for crest in sorted({r["crest"] for r in rows}):
        rs = [r for r in rows if r["crest"] == crest]
        hits = [r for r in rs if r["found_1mm"]]
        cpu = [r["cpu_s"] for r in hits]
        first_ok = [r["first_ok_s"] for r in rs if r["first_ok_s"] is not None]
        out.append({"crest": crest, "runs": len(rs), "found_1mm": len(hits), "share": len(hits) / len(rs),
                    "cpu_s_median": float(np.median(cpu)) if cpu else None,
                    "cpu_s_max": float(np.max(cpu)) if cpu else None,
                    "evaluations_median": float(np.median([r["evaluations"] for r in rs])),
                    "refinements_median": float(np.median([r["refinements"] for r in rs])),
                    "ok_off_2mm": int(sum(r["ok_off_2mm"] for r in rs)),
                    "first_ok_s_median": float(np.median(first_ok)) if first_ok else None})
    return out


def worst(crests: list[dict]) -> dict | None:
    """The worst crest: the lowest share found within 1 mm, then the most CPU to it."""
    return min(crests, key=lambda c: (c["share"], -(c["cpu_s_max"] or np.inf)), default=None)


def table(crests: list[dict]) -> str:
    """A markdown table of :func:`per_crest`."""
    fmt = lambda v, f="{:.2f}": "-" if v is None else f.format(v)  # noqa: E731
    lines = ["| crest | runs | within 1 mm | CPU s to it (median / max) | evaluations / refinements (median) "
             "| frames ok > 2 mm off | first ok s (median) |", "|---|---|---|---|---|---|---|"]
    for c in crests:
        lines.append(f"| {c['crest']} | {c['runs']} | {c['found_1mm']} ({c['share']:.0%}) | "
                     f"{fmt(c['cpu_s_median'])} / {fmt(c['cpu_s_max'])} | {c['evaluations_median']:.0f} / "
                     f"{c['refinements_median']:.0f} | {c['ok_off_2mm']} | {fmt(c['first_ok_s_median'])} |")
    return "\n".join(lines)
