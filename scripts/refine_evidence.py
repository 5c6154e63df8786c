"""Replay trials with the default tracker and keep the refinement's evidence per frame (BENCHMARKS.md §6d).

Usage (from the repository root; run with nice on the shared machine)::

    nice .venv/bin/python scripts/refine_evidence.py TRIAL [TRIAL ...] --out evidence.json
    .venv/bin/python scripts/refine_evidence.py --analyse evidence.json [more.json ...]

Replays each trial (``osteonav replay``'s defaults, no outputs written) and records, for every
refined frame, the kept fit's share of measurements behind the model (``behind``), the share the
image's noise explains (``allowed``, app/filter/refine.py ``behind_bound``), the noise estimate,
the number of measurements (``M``) and of those in the fit (``used``: not buried, not beside a buried
one, inside the robust kernel), the stride used, the fitness, the share within 1 σ (``sharp``), the
predicted template error, the ADD and the status. Prints one summary row per trial (ADD median / p95, rotation median, ok share,
dangerous frames, and the same after the first 0.5 s). ``--analyse`` prints, for margins of the
behind rule (status.max_behind_excess), how many frames the rule declines per scene kind among the
frames otherwise ok-able (after 0.5 s, fitness >= 0.6, template error <= 1 mm) and how many of them
it leaves ok while > 1 mm off.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

SETTLE_FRAMES = 45   # 0.5 s at 90 Hz: the start converges from 5 mm / 3 deg
MARGINS = (0.0, 0.002, 0.003, 0.004, 0.005, 0.01)


def replay_with_evidence(trial: Path) -> dict:
    """One trial: its summary and the refinement's evidence per refined frame."""
    from app.config import load_config
    from app.filter import refine_track
    from app.filter.refine import Refiner
    from app.pipeline.replay import replay
    from app.pipeline.tracker import DepthTracker

    frame, results, rows = [-1], [], []
    process, refine, update = DepthTracker.process, Refiner.refine, refine_track.RefinedTrack.update

    def counted(self, *a, **k):
        frame[0] += 1
        return process(self, *a, **k)

    def recorded(self, depth, T, *a, **k):
        result = refine(self, depth, T, *a, **k)
        results.append((result, self.choose_stride(result.T_camera_bone)[0]))
        return result

    def kept(self, *a, **k):
        results.clear()
        out = update(self, *a, **k)
        fits = [f for f in results if f[0].converged and np.isfinite(f[0].fitness)]
        if fits:
            r, stride = max(fits, key=lambda f: f[0].sharp)     # the track keeps the sharpest fit
            rows.append(dict(frame=frame[0], behind=r.behind, allowed=r.behind_allowed, noise=r.noise, M=r.expected,
                             used=r.used, stride=stride, fitness=r.fitness, sharp=r.sharp, std=out.template_std))
        return out

    DepthTracker.process, Refiner.refine, refine_track.RefinedTrack.update = counted, recorded, kept
    try:
        res = replay(trial, None, load_config(None), rrd=False, projector=False)
    finally:
        DepthTracker.process, Refiner.refine, refine_track.RefinedTrack.update = process, refine, update
    add, statuses = np.asarray(res.errors["add_mm"]), list(res.statuses)
    for r in rows:
        r.update(add=float(add[r["frame"]]), status=str(statuses[r["frame"]]))
    s = res.summary
    return dict(trial=str(trial), summary=dict(add_med=s["add_mm"]["median"], add_p95=s["add_mm"]["p95"],
                rot_med=s["rotation_deg"]["median"], ok=s["status_fraction"]["ok"], dangerous=s["dangerous_frames"],
                lost=s["lost_fraction"], timings=s["timings_ms"]), rows=rows)


def summary_line(t: dict) -> str:
    s = t["summary"]
    late = [r for r in t["rows"] if r["frame"] >= SETTLE_FRAMES]
    add = np.array([r["add"] for r in late])
    ok = np.array([r["status"] == "ok" for r in late])
    return (f"{t['trial']}: ADD median {s['add_med']:.2f} p95 {s['add_p95']:.2f} mm, rotation median {s['rot_med']:.2f} deg, "
            f"ok {s['ok']:.2f}, dangerous {s['dangerous']} | after 0.5 s: ADD median {np.median(add):.2f}, "
            f"ok {ok.mean():.2f}, ok > 1 mm {int(np.sum(ok & (add > 1)))}")


def analyse(runs: list[dict]) -> None:
    kinds = sorted({Path(t["trial"]).name.split("_seed")[0].split("crest_")[-1].split("_", 2)[-1] for t in runs})
    for margin in MARGINS:
        cells = []
        for kind in kinds:
            declined = total = ok_off = 0
            for t in runs:
                if kind not in Path(t["trial"]).name:
                    continue
                rows = [r for r in t["rows"] if r["frame"] >= SETTLE_FRAMES and r["fitness"] >= 0.6 and r["std"] <= 0.001]
                excess = np.array([r["behind"] - r["allowed"] for r in rows])
                add = np.array([r["add"] for r in rows])
                declined += int(np.sum(excess > margin))
                total += len(rows)
                ok_off += int(np.sum((excess <= margin) & (add > 1.0)))
            cells.append(f"{kind}: declined {declined}/{total}, left ok > 1 mm {ok_off}")
        print(f"margin {100 * margin:.1f} % | " + " | ".join(cells))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="*", type=Path)
    ap.add_argument("--out", type=Path, help="JSON of the runs (written after each trial)")
    ap.add_argument("--analyse", nargs="+", type=Path, help="evidence JSON files to analyse instead of replaying")
    args = ap.parse_args()
    if args.analyse:
        analyse([t for f in args.analyse for t in json.loads(f.read_text())])
        return
    if not args.trials:
        raise SystemExit("give trial directories, or --analyse EVIDENCE.json")
    runs = []
    for trial in args.trials:
        runs.append(replay_with_evidence(trial))
        print(summary_line(runs[-1]), flush=True)
        if args.out:
            args.out.write_text(json.dumps(runs))


if __name__ == "__main__":
    main()
