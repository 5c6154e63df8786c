"""Summarise the or_fast_reposition recovery matrix (BENCHMARKS.md, "Recovery: a moved bone found again").

    python scripts/recovery_summary.py repos_s0.json repos_s1.json ...     # `osteonav bench --json` files
    python scripts/recovery_summary.py matrix.jsonl                        # scripts/recovery_matrix.py's lines

Per configuration (one per filter seed): found again within 2 s (app/bench/scoring.py ``refound``:
from the first frame at rest with >= 20 % of the bone in view to the first frame from which ADD
stays < 2 mm to the end; ``refound_s`` <= 2.0 s), the slowest, runs found late or never, refound
mean / p90, the ok share (median / min / mean over runs), frames ok while more than 1, 2 and 5 mm off
(the last is the bench's ``danger``), and the wide searches (count, CPU s each). A run is named
``crest#trial-seed`` from its trial folder (``<crest>/or_fast_reposition_seed<N>``).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

WITHIN_S = 2.0


def load_rows(paths: list[str]) -> tuple[list[dict], list[dict]]:
    """(run rows, other records) from bench JSON files (``{"rows": [...]}``) or JSON-lines files."""
    rows, other = [], []
    for p in paths:
        text = Path(p).read_text()
        try:
            data = json.loads(text)
            records = data["rows"] if isinstance(data, dict) and "rows" in data else [data]
        except json.JSONDecodeError:
            records = [json.loads(line) for line in text.splitlines() if line.strip()]
        for r in records:
            (rows if r.get("kind", "run") == "run" and "error" not in r and "refound" in r else other).append(r)
    return rows, other


def run_name(row: dict) -> str:
    p = Path(row["trial_path"])
    seed = p.name.rsplit("seed", 1)[1] if "seed" in p.name else "?"
    return f"{p.parent.name}#{seed}"


def summarise(rows: list[dict]) -> dict:
    """One configuration's figures (module docstring)."""
    found, never, not_in_view, ok_pct, searches, search_cpu = [], [], [], [], 0, []
    ok_off = {1.0: [], 2.0: [], 5.0: []}
    for r in sorted(rows, key=run_name):
        name, f = run_name(r), r["refound"]
        if f is None or f["visible_s"] is None:
            not_in_view.append(name)
        elif f["refound_s"] is None:
            never.append(name)
        else:
            found.append((f["refound_s"], name))
        ok_pct.append(r["status_pct"]["ok"])
        add = np.asarray(r["series"]["add_mm"], float)
        ok = np.asarray(r["series"]["status"]) == "ok"
        for level, runs in ok_off.items():
            n = int(np.sum(ok & (add > level)))
            if n:
                runs.append((name, n, float(add[ok & (add > level)].min()), float(add[ok & (add > level)].max())))
        s = (r.get("recovery") or {}).get("search") or {}
        searches += int(s.get("searches", 0))
        if s.get("searches"):
            search_cpu.append(s["cpu_s"] / s["searches"])
    times = np.array([t for t, _ in found])
    return {
        "runs": len(rows), "within": sum(t <= WITHIN_S for t, _ in found),
        "slowest": max(found) if found else None,
        "late": sorted([(t, n) for t, n in found if t > WITHIN_S], reverse=True), "never": never,
        "not_in_view": not_in_view,
        "refound_mean": float(times.mean()) if len(times) else None,
        "refound_p90": float(np.percentile(times, 90)) if len(times) else None,
        "ok_pct": (float(np.median(ok_pct)), float(np.min(ok_pct)), float(np.mean(ok_pct))),
        "ok_off": {level: (sum(n for _, n, _, _ in runs), runs) for level, runs in ok_off.items()},
        "searches": searches,
        "search_cpu_s": (float(np.mean(search_cpu)), float(np.min(search_cpu)), float(np.max(search_cpu))) if search_cpu else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+")
    args = ap.parse_args()
    rows, other = load_rows(args.files)
    for o in other:
        if o.get("kind") in ("end", "error") or o.get("error"):
            print("note:", {k: v for k, v in o.items() if k not in ("tb", "tail")})
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["config"], []).append(r)
    print("| config | found within 2 s | slowest (s) | late / never | refound mean / p90 (s) | ok %: median / min / mean "
          "| ok while > 1 / 2 / 5 mm off (frames) | searches (CPU s each, mean) |")
    print("|---|---|---|---|---|---|---|---|")
    details = []
    for cfg in sorted(by):
        s = summarise(by[cfg])
        slow = f"{s['slowest'][0]:.2f} ({s['slowest'][1]})" if s["slowest"] else "-"
        late = ", ".join([f"{n} {t:.2f} s" for t, n in s["late"]] + [f"{n} never" for n in s["never"]]) or "-"
        mean = "-" if s["refound_mean"] is None else f"{s['refound_mean']:.2f} / {s['refound_p90']:.2f}"
        off = " / ".join(str(s["ok_off"][lv][0]) for lv in (1.0, 2.0, 5.0))
        cpu = "" if s["search_cpu_s"] is None else f" ({s['search_cpu_s'][0]:.2f})"
        print(f"| {cfg} | {s['within']} of {s['runs']} | {slow} | {late} | {mean} | "
              f"{s['ok_pct'][0]:.1f} / {s['ok_pct'][1]:.1f} / {s['ok_pct'][2]:.1f} | {off} | {s['searches']}{cpu} |")
        for level in (1.0, 2.0, 5.0):
            for name, n, lo, hi in s["ok_off"][level][1]:
                details.append(f"{cfg}: {name}: {n} frames ok while > {level:g} mm off (ADD {lo:.2f}-{hi:.2f} mm)")
        if s["not_in_view"]:
            details.append(f"{cfg}: never in view after rest: {', '.join(s['not_in_view'])}")
    print()
    print("\n".join(details) if details else "no frame ok while more than 1 mm off")
    total = sum(len(v) for v in by.values())
    print(f"\nall configurations: found within 2 s {sum(summarise(v)['within'] for v in by.values())} of {total}")


if __name__ == "__main__":
    main()
