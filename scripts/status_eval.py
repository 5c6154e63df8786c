"""Score the status on replayed simulated trials: ok where it should be, never ok where it must not be.

    python scripts/status_eval.py OUT_ROOT [--json FILE]

OUT_ROOT holds replay outputs as ``OUT_ROOT/<label>/<crest>/<scenario>/`` (estimate.txt, status.csv,
summary.json, whose ``trial`` names the simulated trial with its groundtruth.txt and simulation.csv).
Per run and per label (issue 32's targets):

- ``eligible_ok``: the share of the *eligible* frames that are ok. Eligible: at least 60 % of the
  bone visible (1 − the simulator's occluded share >= 0.6, and its pixels >= 0.6 of the trial's 95th
  percentile), at rest (the true pose unchanged over the last ``REST_S``) and the estimate less than
  1 mm off (ADD);
- ``ok_over_2mm``: frames ok while ADD > 2 mm (must be 0);
- ``ok_template_over_1mm``: frames ok while the plan's largest point error exceeds the 1 mm tolerance (the
  status's own promise; what a surgeon would cut by);
- ``template_median_mm``: the median over frames of the plan's largest point error (what the surgeon
  would see; the default projector configuration's plan on the mesh);
- ``blocked_by``: among the eligible frames not ok, the share each reason code kept from ok
  (status.csv's ``reasons`` column; none for a status.csv without it).
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REST_S = 0.3
VISIBLE = 0.6
GOOD_MM = 1.0
DANGER_MM = 2.0


def _status_rows(path: Path) -> tuple[list[str], list[tuple[str, ...]]]:
    lines = path.read_text().splitlines()
    statuses, reasons = [], []
    for line in lines[1:]:
        if not line.strip():
            continue
        f = line.split(",")
        statuses.append(f[1])
        reasons.append(tuple(c for c in f[3].split(";") if c) if len(f) > 3 else ())
    return statuses, reasons


def score_run(out: Path) -> dict:
    import trimesh

    from app import metrics
    from app.trial import tum
    summary = json.loads((out / "summary.json").read_text())
    trial = Path(summary["trial"])
    t_gt, T_gt = tum.read_tum(trial / "groundtruth.txt")
    t_est, T_est = tum.read_tum(out / "estimate.txt")
    statuses, reasons = _status_rows(out / "status.csv")
    sim = np.genfromtxt(trial / "simulation.csv", delimiter=",", names=True)
    mesh_name = next(p for p in trial.iterdir() if p.suffix in (".ply", ".stl", ".obj"))
    mesh = trimesh.load(mesh_name)
    points = np.asarray(mesh.vertices)[::10]
    from app.pipeline.replay import known_plan
    plan, _ = known_plan(None, mesh)
    plan_points = np.asarray(plan.points(), float) if plan is not None else points
    n = min(len(t_est), len(statuses), len(t_gt))
    index = np.searchsorted(t_gt, t_est[:n] - 1e-6)
    add = np.array([1e3 * metrics.add(T_est[k], T_gt[j], points) for k, j in enumerate(index)])
    template = np.array([1e3 * metrics.mdd(T_est[k], T_gt[j], plan_points) for k, j in enumerate(index)])
    ok = np.array(statuses[:n]) == "ok"
    pixels = np.asarray(sim["bone_pixels"], float)[index]
    visible = ((1.0 - np.asarray(sim["occlusion"], float)[index]) >= VISIBLE) & \
              (pixels >= VISIBLE * np.percentile(sim["bone_pixels"], 95))
    moved = np.r_[True, np.any(np.abs(T_gt[1:] - T_gt[:-1]) > 1e-9, axis=(1, 2))]
    last_move = np.maximum.accumulate(np.where(moved, t_gt, -np.inf))
    rest = (t_gt - last_move >= REST_S)[index]
    eligible = visible & rest & (add < GOOD_MM)
    blocked = Counter(c for k in np.nonzero(eligible & ~ok)[0] for c in set(reasons[k]))
    n_el = int(eligible.sum())
    return {"frames": n, "eligible": n_el, "eligible_ok": float(ok[eligible].mean()) if n_el else float("nan"),
            "ok": float(ok.mean()), "ok_over_2mm": int(np.sum(ok & (add > DANGER_MM))),
            "ok_template_over_1mm": int(np.sum(ok & (template > GOOD_MM))),
            "add_median_mm": float(np.median(add)), "template_median_mm": float(np.median(template)),
            "eligible_template_over_1mm": int(np.sum(eligible & (template > GOOD_MM))), "max_ok_add_mm": float(add[ok].max()) if ok.any() else 0.0,
            "blocked_by": {c: v / max(int((eligible & ~ok).sum()), 1) for c, v in blocked.most_common()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = {}
    for summary in sorted(args.root.glob("*/*/*/summary.json")):
        out = summary.parent
        label, crest, scenario = out.parts[-3:]
        rows.setdefault(label, {})[f"{crest}/{scenario}"] = score_run(out)
    for label, runs in rows.items():
        print(f"\n## {label}")
        print(f"{'run':42s} {'elig':>5s} {'ok|elig':>8s} {'ok':>6s} {'>2mm':>5s} {'tmpl>1':>6s} {'ADDmed':>7s} {'tmpl':>6s}  blocked_by")
        for name, r in runs.items():
            blocked = ", ".join(f"{c} {100 * v:.0f}%" for c, v in list(r["blocked_by"].items())[:4])
            print(f"{name:42s} {r['eligible']:5d} {100 * r['eligible_ok']:7.1f}% {100 * r['ok']:5.1f}% "
                  f"{r['ok_over_2mm']:5d} {r['ok_template_over_1mm']:6d} {r['add_median_mm']:7.3f} {r['template_median_mm']:6.2f}  {blocked}")
        shares = [r["eligible_ok"] for r in runs.values() if np.isfinite(r["eligible_ok"])]
        if shares:
            print(f"{'median / worst':42s} {'':5s} {100 * np.median(shares):7.1f}% / {100 * min(shares):.1f}%  "
                  f"ok over 2 mm: {sum(r['ok_over_2mm'] for r in runs.values())}, "
                  f"ok with the template over 1 mm: {sum(r['ok_template_over_1mm'] for r in runs.values())}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
