"""Human-readable tables of replay summaries (commands print them; the library does not)."""
from __future__ import annotations


def summary_rows(summary: dict) -> list[tuple[str, str]]:
    rows = [
        ("frames", f"{summary['frames']}"),
        ("processing rate", f"{summary['processing_rate_hz']:.1f} frames/s  ({summary.get('gl', '?')})"),
        ("particles / resolution", f"{summary['particles']} at {summary['resolution'][0]}x{summary['resolution'][1]}, {summary['sampling']}"),
    ]
    init = summary.get("init")
    if init:
        text = (f"one-point initialiser: {init['seconds']:.1f} s, {init['tempering_steps']} tempering steps"
                + (f", off by {init['add_mm']:.1f} mm ADD / {init['rotation_deg']:.1f} deg" if "add_mm" in init else "")
                + " (experimental: never ok)")
        rows.append(("start", text))
    start = summary.get("start")
    if start:
        rows.append(("start", start_text(start)))
    if "add_mm" in summary:
        a, t, r = summary["add_mm"], summary["translation_mm"], summary["rotation_deg"]
        rows += [
            ("ADD mm (median / p95 / max)", f"{a['median']:.2f} / {a['p95']:.2f} / {a['max']:.2f}"),
            ("translation mm", f"{t['median']:.2f} / {t['p95']:.2f} / {t['max']:.2f}"),
            ("rotation deg", f"{r['median']:.2f} / {r['p95']:.2f} / {r['max']:.2f}"),
            ("lost (ADD > 10 mm)", f"{100 * summary['lost_fraction']:.1f} %"),
            ("dangerous (ok, ADD > 5 mm)", f"{summary['dangerous_frames']} frames"),
        ]
    recovery = summary.get("recovery")
    if recovery and recovery.get("enabled"):
        rows.append(("recovery", recovery_text(recovery)))
    s = summary["status_fraction"]
    rows.append(("status ok / uncertain / lost", f"{100 * s['ok']:.0f} / {100 * s['uncertain']:.0f} / {100 * s['lost']:.0f} %"))
    blocked = summary.get("blocked_by") or {}
    if blocked:   # why the template was not shown (status.csv's reason codes; README's table)
        rows.append(("not ok because (share of frames)",
                     ", ".join(f"{code} {100 * share:.0f} %" for code, share in list(blocked.items())[:5])))
    p = summary.get("projector")
    if p and p.get("skipped"):
        rows.append(("projector", f"skipped: {p['skipped']}"))
    elif p:
        shown = f"plan {p.get('plan')}; template shown in {p['template_shown']} of {p['frames']} projector frames"
        if "template_error_mean_mm" in p:
            shown += (f"; outline on the bone off by {p['template_error_mean_mm']:.2f} mm mean, "
                      f"{p['template_error_p95_mm']:.2f} p95, {p['template_error_max_mm']:.2f} max")
        rows.append(("projector", shown))
    return rows


def recovery_text(recovery: dict) -> str:
    """The recovery's re-initialisations and wide searches in a line (app/filter/recovery.py report)."""
    events = recovery.get("events", [])
    count = recovery.get("reinitialisations", len(events))
    text = f"{count} re-initialisation{'' if count == 1 else 's'}"
    if events:
        stamps = ", ".join(f"{e['kind']} at {e['stamp']:.2f} s" + (f" ({e['trigger']})" if e.get("trigger") else "")
                           for e in events[:4])
        text += f" ({stamps}{', ...' if len(events) > 4 else ''})"
    search = recovery.get("search") or {}
    if search.get("searches"):
        text += (f"; {search['searches']} wide searches: {search.get('found', 0)} found a pose, "
                 f"{search.get('kept', 0)} kept the track, {recovery.get('declined_searches', 0)} found nothing")
    return text


def print_summary(summary: dict) -> None:
    rows = summary_rows(summary)
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"  {key:<{width}}  {value}")


def start_text(start: dict) -> str:
    """The detected start (summary's ``start`` block, init.method auto without a pose) in one line."""
    where = {"detect_point": "from the point",
             "detect_pointed": f"from the {start.get('source', 'pointed point')}"}.get(
        start["method"], "over the whole image (experimental)")
    work = (f"{start['attempts']} attempt(s), {start['evaluations']} evaluations, {start['refinements']} refinements, "
            f"{start['cpu_s']:.2f} s CPU")
    if start["method"] == "detect_pointed" and start.get("point") is None:
        return f"detector {where}: never located ({start.get('waiting') or 'no usable frame'}; {work})"
    if not start["found"]:
        return f"detector {where}: the bone not found ({work})"
    return f"detector {where}: found on the frame stamped {start['found_stamp']:.3f} s ({work}); ok once confirmed"
