"""The bench's outputs: the table, the JSON and the plots."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from app.metrics import DANGEROUS_ADD_MM, LOST_ADD_MM


COLUMNS = ("config", "scenario", "fps", "ADD med", "ADD p95", "rot med", "rot p95", "VSD rec",
           "lost %", "ok %", "danger", "jit mm", "jit deg", "refound s", "ADD cam", "outline max")


def _row_cells(r: dict) -> list[str]:
    def f(x, digits=2):
        return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"

    return [r["config"], r["trial"], f(r["fps"], 1), f(r["add_mm"]["median"]), f(r["add_mm"]["p95"]),
            f(r["rotation_deg"]["median"]), f(r["rotation_deg"]["p95"]), f(r["vsd_recall"]),
            f(r["lost_pct"], 1), f(r["status_pct"]["ok"], 1), str(r["dangerous_frames"]),
            f(r["jitter"]["translation_mm"], 3), f(r["jitter"]["rotation_deg"], 3), _refound_cell(r.get("refound")),
            f(_template(r, "add_camera_mm", "median")), f(_template(r, "outline_max_mm"))]


def _template(r: dict, key: str, sub: str | None = None) -> float:
    """A value of the row's ``template`` block (app/bench/template.py); NaN when the row has none."""
    value = (r.get("template") or {}).get(key)
    if sub is not None and isinstance(value, dict):
        value = value.get(sub)
    return float("nan") if value is None else float(value)


def _refound_cell(found: dict | None) -> str:
    """refound_s of a run (app/bench/scoring.py's ``refound``): seconds, 'never', 'not in view' or '-'."""
    if found is None:
        return "-"
    if found["visible_s"] is None:
        return "not in view"
    return "never" if found["refound_s"] is None else f"{found['refound_s']:.2f}"


def refound_stat(rows: list[dict], who: list[str]) -> dict:
    """Over runs with a moved bone that came into view after rest: the median and the worst
    ``refound_s`` (a run never found again counts as worst, inf), and the runs never found / never in view."""
    seen = [(w, r["refound"]) for w, r in zip(who, rows) if r.get("refound") and r["refound"]["visible_s"] is not None]
    values = np.array([np.inf if f["refound_s"] is None else f["refound_s"] for _, f in seen], float)
    out = {"runs": len(seen), "median": None, "worst": None, "worst_run": None,
           "never": [w for w, f in seen if f["refound_s"] is None],
           "not_in_view": [w for w, r in zip(who, rows) if r.get("refound") and r["refound"]["visible_s"] is None]}
    if len(values):
        k = int(np.argmax(values))
        out.update(median=float(np.median(values)), worst=float(values[k]), worst_run=seen[k][0])
    return out


def table(rows: list[dict], markdown: bool = False) -> str:
    """The results table: one row per configuration x trial (ADD mm, rotation deg)."""
    cells = [_row_cells(r) for r in rows]
    header = list(COLUMNS)
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(c) + " |" for c in cells]
        return "\n".join(lines)
    widths = [max(len(h), *(len(c[i]) for c in cells)) if cells else len(h) for i, h in enumerate(header)]
    fmt = lambda cs: "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(cs, widths)))  # noqa: E731
    lines = [fmt(header), "-" * len(fmt(header))]
    previous = None
    for r, c in zip(rows, cells):
        if previous is not None and r["trial"] != previous:
            lines.append("")
        previous = r["trial"]
        lines.append(fmt(c))
    return "\n".join(lines)


SUMMARY_COLUMNS = ("config", "scenario", "runs", "ADD med: median / worst", "ADD p95: median / worst",
                   "rot med: median / worst", "lost %: median / worst", "ok %: median / min", "danger (total)",
                   "after rest + 0.3 s: max ADD worst", "refound s: median / worst",
                   "ADD cam med: median / worst", "outline max on ok: median / worst")


def summary(rows: list[dict]) -> list[dict]:
    """Per configuration x scenario, over meshes and seeds: the median run and the worst run (named
    ``mesh#seed``) of ADD median / p95, rotation median, lost %, ok % (worst = least), the dangerous
    frames in total, for a moving bone the worst max ADD from 0.3 s after it comes to rest, and the
    camera-frame ADD median and the projected outline's largest displacement on ok frames
    (app/bench/template.py)."""
    out = []
    for key in dict.fromkeys((r["config"], r["scenario"]) for r in rows):
        rs = [r for r in rows if (r["config"], r["scenario"]) == key]
        who = [f"{r['mesh']}#{r.get('seed', 0)}" for r in rs]

        def stat(values, worst=np.nanargmax):
            v = np.asarray(values, float)
            if not np.isfinite(v).any():
                return {"median": float("nan"), "worst": float("nan"), "worst_run": None}
            k = int(worst(v))
            return {"median": float(np.nanmedian(v)), "worst": float(v[k]), "worst_run": who[k]}

        rest = [r["after_rest"]["max_add_mm"] if r.get("after_rest") else np.nan for r in rs]
        out.append({"config": key[0], "scenario": key[1], "runs": len(rs),
                    "add_median": stat([r["add_mm"]["median"] for r in rs]),
                    "add_p95": stat([r["add_mm"]["p95"] for r in rs]),
                    "rot_median": stat([r["rotation_deg"]["median"] for r in rs]),
                    "lost_pct": stat([r["lost_pct"] for r in rs]),
                    "ok_pct": stat([r["status_pct"]["ok"] for r in rs], worst=np.nanargmin),
                    "dangerous_frames": int(sum(r["dangerous_frames"] for r in rs)),
                    "dangerous_runs": [w for w, r in zip(who, rs) if r["dangerous_frames"]],
                    "after_rest_max_add": stat(rest), "refound_s": refound_stat(rs, who),
                    "add_camera_median": stat([_template(r, "add_camera_mm", "median") for r in rs]),
                    "outline_max": stat([_template(r, "outline_max_mm") for r in rs])})
    return out


def _refound_summary(st: dict) -> str:
    """'median / worst (run)' of refound_s, 'never' for an inf worst, with the runs never in view."""
    if st["runs"] == 0:
        return "-" if not st["not_in_view"] else f"not in view ({len(st['not_in_view'])})"
    worst = "never" if not np.isfinite(st["worst"]) else f"{st['worst']:.2f}"
    median = "never" if not np.isfinite(st["median"]) else f"{st['median']:.2f}"
    text = f"{median} / {worst} ({st['worst_run']})"
    return text + (f", not in view: {len(st['not_in_view'])}" if st["not_in_view"] else "")


def summary_table(rows: list[dict], markdown: bool = False) -> str:
    """:func:`summary` as a table: 'median / worst (worst run)' per cell."""
    def cell(st, digits=2):
        if st["worst_run"] is None:
            return "-"
        return f"{st['median']:.{digits}f} / {st['worst']:.{digits}f} ({st['worst_run']})"

    lines = []
    for s in summary(rows):
        danger = str(s["dangerous_frames"]) + (f" ({', '.join(s['dangerous_runs'])})" if s["dangerous_runs"] else "")
        rest = "-" if s["after_rest_max_add"]["worst_run"] is None else \
            f"{s['after_rest_max_add']['worst']:.2f} ({s['after_rest_max_add']['worst_run']})"
        lines.append([s["config"], s["scenario"], str(s["runs"]), cell(s["add_median"]), cell(s["add_p95"]),
                      cell(s["rot_median"]), cell(s["lost_pct"], 1), cell(s["ok_pct"], 1), danger, rest,
                      _refound_summary(s["refound_s"]), cell(s["add_camera_median"]), cell(s["outline_max"])])
    header = list(SUMMARY_COLUMNS)
    if markdown:
        return "\n".join(["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
                         + ["| " + " | ".join(c) + " |" for c in lines])
    return "\n".join([" | ".join(header)] + [" | ".join(c) for c in lines])


def write_json(rows: list[dict], path: str | Path, meta: dict | None = None) -> None:
    """The rows (with per-frame series) and run information as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return x

    tmp = path.with_suffix(path.suffix + ".part")   # written whole, then renamed: a partial matrix stays readable
    tmp.write_text(json.dumps(clean({"meta": meta or {}, "summary": summary(rows), "columns": {
        "fps": "processed frames per second of the replay loop (wall time) on this machine",
        "add_mm": "ADD, mm", "rotation_deg": "rotation error, deg", "vsd_recall": "fraction of frames with e_VSD < 0.3 (tau 20 mm)",
        "lost_pct": f"% frames with ADD > {LOST_ADD_MM} mm", "dangerous_frames": f"frames with status ok and ADD > {DANGEROUS_ADD_MM} mm",
        "jitter": "RMS frame-to-frame change of the estimate while the ground truth is static (after settling)",
        "template": "the projected outline on the real bone on ok frames and the camera-frame ADD (app/bench/template.py)",
    }, "rows": rows}), indent=1))
    tmp.replace(path)


def plot(rows: list[dict], folder: str | Path) -> list[Path]:
    """PNGs: ADD over time per configuration for each trial, and frames/s per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from app.outputs import wrote

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    configs = list(dict.fromkeys(r["config"] for r in rows))
    colours = {c: plt.get_cmap("tab10")(k % 10) for k, c in enumerate(configs)}
    for trial in dict.fromkeys(r["trial"] for r in rows):
        fig, (ax_add, ax_rot) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for r in (r for r in rows if r["trial"] == trial):
            s = r["series"]
            ax_add.plot(s["t"], s["add_mm"], label=r["config"], color=colours[r["config"]], lw=1)
            danger = [(t, a) for t, a, st in zip(s["t"], s["add_mm"], s["status"]) if st == "ok" and a > DANGEROUS_ADD_MM]
            if danger:
                ax_add.plot(*zip(*danger), "x", color=colours[r["config"]], ms=5)
            ax_rot.plot(s["t"], s["rot_deg"], color=colours[r["config"]], lw=1)
        ax_add.axhline(DANGEROUS_ADD_MM, color="grey", ls="--", lw=0.8)   # x: status ok above this line
        ax_add.set_yscale("log")
        ax_add.set_ylabel("ADD (mm)")
        ax_rot.set_yscale("log")
        ax_rot.set_ylabel("rotation error (deg)")
        ax_rot.set_xlabel("time (s)")
        ax_add.set_title(f"error over time: {trial}")
        ax_add.legend(fontsize=8, ncol=3)
        fig.tight_layout()
        path = folder / f"error_{trial.replace('/', '__')}.png"
        wrote(path)
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(configs)), 4))
    fps = [[r["fps"] for r in rows if r["config"] == c] for c in configs]
    ax.bar(range(len(configs)), [np.mean(v) for v in fps], color=[colours[c] for c in configs])
    for k, v in enumerate(fps):
        ax.plot([k] * len(v), v, "k.", ms=4)
    ax.set_xticks(range(len(configs)), configs, rotation=20, ha="right")
    ax.set_ylabel("frames / s (mean over trials; dots: each trial)")
    ax.set_title("processing rate per configuration")
    fig.tight_layout()
    path = folder / "rate.png"
    wrote(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    written.append(path)
    return written
