"""Measure the automatic recovery (app/filter/recovery.py) on the eight shared CT crests (BENCHMARKS.md §6b).

Usage (from the repository root; run with nice on the shared machine)::

    nice .venv/bin/python scripts/recovery_crests.py --scenario static_occluded --seconds 5 --seeds 0 \
        --variants off on --out /tmp/recovery_crests.json

For each crest x seed it simulates a trial (cached, as scripts/refine_crests.py) and replays it with
recovery off (``recovery.enabled: false``, the default) and on (enabled, its other defaults), and prints one
row per run and the median / worst per variant: the lost share (ADD > 10 mm), the dangerous frames
(ok while ADD > 5 mm), the re-initialisations, the longest stretch with ADD > 5 mm (s of trial time),
the ADD median over the last second, whether the run ends found (ADD < 2 mm), and for each
re-initialisation the time until ADD < 2 mm.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from refine_crests import selected_crests, trial_path  # noqa: E402


def variant_config(name: str):
    from app.config import load_config

    config = load_config(None)
    if name == "off":
        return replace(config, recovery=replace(config.recovery, enabled=False))
    if name == "on":
        return replace(config, recovery=replace(config.recovery, enabled=True))
    raise SystemExit(f"unknown variant {name!r}: off | on")


def longest_run(mask: np.ndarray, stamps: np.ndarray) -> float:
    """Longest stretch (s) of consecutive True frames."""
    best, start = 0.0, None
    for i, m in enumerate(mask):
        if m and start is None:
            start = i
        if start is not None and (not m or i == len(mask) - 1):
            end = i if m else i - 1
            best = max(best, float(stamps[end] - stamps[start]))
            start = None
    return best


def time_to_found(stamps: np.ndarray, add: np.ndarray, t0: float) -> float:
    """Seconds from t0 until the first frame with ADD < 2 mm (inf if never)."""
    after = np.nonzero((stamps >= t0) & (add < 2.0))[0]
    return float(stamps[after[0]] - t0) if after.size else float("inf")


def run(trial: Path, variant: str) -> dict:
    from app.pipeline.replay import replay

    result = replay(trial, None, variant_config(variant), rrd=False, projector=False)
    s, add = result.summary, result.errors["add_mm"]
    stamps = np.asarray(result.stamps) - result.stamps[0]
    events = s.get("recovery", {}).get("events", [])
    t_rec = [time_to_found(stamps, add, e["stamp"] - result.stamps[0]) for e in events]
    last = stamps >= stamps[-1] - 1.0
    return {"add_med": s["add_mm"]["median"], "lost": s["lost_fraction"], "dangerous": s["dangerous_frames"],
            "ok": s["status_fraction"]["ok"], "reinits": len(events),
            "kinds": ",".join(e["kind"] for e in events), "longest_off_s": longest_run(add > 5.0, stamps),
            "add_last_1s": float(np.median(add[last])), "found_at_end": bool(add[-1] < 2.0),
            "t_to_found": [round(t, 2) for t in t_rec], "frames": s["frames"]}


def summarise(rows: list[dict]) -> None:
    print("\nvariant | runs | lost share (median / max) | dangerous (total) | re-inits (total) | longest > 5 mm s "
          "(median / max) | ADD last 1 s (median / max) | found at end | ok share (median)")
    for variant in sorted({r["variant"] for r in rows}):
        rs = [r for r in rows if r["variant"] == variant]
        a = lambda k: np.array([r[k] for r in rs], float)  # noqa: E731
        print(f"{variant} | {len(rs)} | {np.median(a('lost')):.2f} / {a('lost').max():.2f} | {int(a('dangerous').sum())} | "
              f"{int(a('reinits').sum())} | {np.median(a('longest_off_s')):.2f} / {a('longest_off_s').max():.2f} | "
              f"{np.median(a('add_last_1s')):.2f} / {a('add_last_1s').max():.2f} | "
              f"{int(a('found_at_end').sum())}/{len(rs)} | {np.median(a('ok')):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="static_occluded")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--variants", nargs="+", default=["off", "on"])
    ap.add_argument("--crests", nargs="+", default=None, help="crest stems (default: all crest_*.ply)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/osteonav_refine_trials"))
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    crests = selected_crests(args.crests)
    rows = []
    for seed in args.seeds:
        for crest in crests:
            trial = trial_path(args.cache, crest, args.scenario, args.seconds, seed)
            for variant in args.variants:
                row = {"crest": crest.stem, "seed": seed, "variant": variant, **run(trial, variant)}
                rows.append(row)
                print(" ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
                if args.out:
                    args.out.write_text(json.dumps(rows, indent=1))
    summarise(rows)


if __name__ == "__main__":
    main()
