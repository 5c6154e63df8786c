"""Measure the local refinement and the status on the eight shared CT crests (BENCHMARKS.md §6).

Usage (from the repository root; short trials, run with nice on the shared machine)::

    nice .venv/bin/python scripts/refine_crests.py --scenarios static_clear or_model_mismatch \
        --seconds 2 --seeds 0 --variants off on --out /tmp/refine_crests.json

For each crest x scenario x seed it simulates a trial (cached under --cache), replays it with each
variant (``off``: the default tracker without refinement; ``on``: with it; ``nofeedback``: refined,
the cloud not shifted; ``nobehind``: without the status's behind-the-model rule) and prints one row per run plus the median / worst per variant and scenario:
ADD median / p95 / max (mm), rotation median (deg), the ok share, the dangerous frames (status ok
while ADD > 5 mm), the lost fraction and the refinement's share of the frame time, and the ok share after the first second (the start converges from 5 mm / 3 deg and
settles for 0.3 s). Writes the rows
as JSON.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PELVIS = REPO.parent / "shared" / "data" / "pelvis"


def variant_config(name: str):
    from app.config import load_config

    config = load_config(None)
    if name == "off":
        return replace(config, refine=replace(config.refine, enabled=False))
    if name == "nofeedback":
        return replace(config, refine=replace(config.refine, feedback=False))
    if name == "nobehind":
        return replace(config, status=replace(config.status, max_behind_excess=float("inf")))
    if name == "on":
        return config
    raise SystemExit(f"unknown variant {name!r}: off | on | nofeedback | nobehind")


def trial_path(cache: Path, crest: Path, scenario: str, seconds: float, seed: int) -> Path:
    from app.sim.simulator import simulate

    out = cache / f"{crest.stem}_{scenario}_{seconds:g}s_seed{seed}"
    if not (out / "groundtruth.txt").is_file() or (out / ".recording-in-progress").exists():
        simulate(out, mesh_path=crest, scenario_name=scenario, seconds=seconds, seed=seed, overwrite=True)
    return out


def run(trial: Path, variant: str) -> dict:
    from app.pipeline.replay import replay

    result = replay(trial, None, variant_config(variant), rrd=False, projector=False)
    s = result.summary
    late = np.asarray(result.stamps) - result.stamps[0] >= 1.0
    ok_late = float(np.mean([st == "ok" for st, keep in zip(result.statuses, late) if keep])) if late.any() else float("nan")
    add = np.asarray(result.errors["add_mm"])
    ok = np.asarray(result.statuses) == "ok"
    t = s["timings_ms"]
    total = sum(v for k, v in t.items() if not k.startswith("gl_"))
    return {"add_med": s["add_mm"]["median"], "add_p95": s["add_mm"]["p95"], "add_max": s["add_mm"]["max"],
            "rot_med": s["rotation_deg"]["median"], "ok": s["status_fraction"]["ok"], "ok_after_1s": ok_late,
            "dangerous": s["dangerous_frames"],
            "ok_over_1mm": int(np.sum(ok & (add > 1.0))), "ok_over_2mm": int(np.sum(ok & (add > 2.0))), "lost": s["lost_fraction"], "frames": s["frames"],
            "refine_ms": t.get("refine", 0.0), "frame_ms": total}


def summarise(rows: list[dict]) -> None:
    keys = sorted({(r["scenario"], r["variant"]) for r in rows})
    print("\nscenario | variant | runs | ADD med (median / worst) | ADD p95 worst | rot med (median / worst) | "
          "ok share (median / min) | ok after 1 s (median / min) | dangerous (total) | lost (max) | refine ms / frame ms")
    for scenario, variant in keys:
        rs = [r for r in rows if r["scenario"] == scenario and r["variant"] == variant]
        a = lambda k: np.array([r[k] for r in rs], float)  # noqa: E731
        print(f"{scenario} | {variant} | {len(rs)} | {np.median(a('add_med')):.2f} / {a('add_med').max():.2f} | "
              f"{a('add_p95').max():.2f} | {np.median(a('rot_med')):.2f} / {a('rot_med').max():.2f} | "
              f"{np.median(a('ok')):.2f} / {a('ok').min():.2f} | "
              f"{np.nanmedian(a('ok_after_1s')):.2f} / {np.nanmin(a('ok_after_1s')):.2f} | {int(a('dangerous').sum())} | {a('lost').max():.2f} | "
              f"{np.median(a('refine_ms')):.0f} / {np.median(a('frame_ms')):.0f}")


def selected_crests(stems: list[str] | None) -> list[Path]:
    """The crest_*.ply of ../shared/data/pelvis, only ``stems`` when given; exits when there is none."""
    crests = sorted(PELVIS.glob("crest_*.ply"))
    if stems:
        crests = [c for c in crests if c.stem in stems]
    if not crests:
        raise SystemExit(f"no crest_*.ply in {PELVIS}")
    return crests


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["static_clear"])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--variants", nargs="+", default=["off", "on"])
    ap.add_argument("--crests", nargs="+", default=None, help="crest stems (default: all crest_*.ply)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/osteonav_refine_trials"))
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    crests = selected_crests(args.crests)
    rows = []
    for scenario in args.scenarios:
        for seed in args.seeds:
            for crest in crests:
                trial = trial_path(args.cache, crest, scenario, args.seconds, seed)
                for variant in args.variants:
                    row = {"crest": crest.stem, "scenario": scenario, "seed": seed, "variant": variant, **run(trial, variant)}
                    rows.append(row)
                    print(" ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
                    if args.out:
                        args.out.write_text(json.dumps(rows, indent=1))
    summarise(rows)


if __name__ == "__main__":
    main()
