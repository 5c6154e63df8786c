"""``osteonav track --config SESSION.yaml``: the intraoperative tracking loop, until stopped.

Ctrl-C ends it cleanly: sources stop, the recording and logs are flushed, and the summary
(frames, statuses, events, frame-to-estimate latency median and p99) is printed and written to
``out/summary.json``. See :mod:`app.session` for the session file.
"""
from __future__ import annotations

from app.cli_types import deprecated_alias, positive_seconds
from app.commands.outdir import add_overwrite_argument, prepare_dir, prepare_file


def register(subparsers) -> None:
    p = subparsers.add_parser("track", help="run a tracking session (camera + robot + tracker) until stopped")
    add_session_arguments(p)
    p.add_argument("--record", metavar="DIR", help="also record the sensors as a trial in DIR (default: the session file's record, else none)")
    p.add_argument("--soak", action="store_true", help="a soak run of the loop itself: no outputs and no recording "
                   "(disk), recorded/simulated sources loop; the summary gives memory (RSS) and rate at start and end")
    p.set_defaults(func=run)


def add_session_arguments(p) -> None:
    p.add_argument("--config", required=True, help="session YAML (see configs/sessions/)")
    p.add_argument("--out", help="directory for estimate.txt, status.csv, events.csv, summary.json (default: the session file's out)")
    add_seconds_argument(p)
    add_overwrite_argument(p, "the outputs (out, record) of an earlier session")


def add_seconds_argument(p) -> None:
    """``--seconds S`` (deprecated: ``--duration``): stop after S > 0 seconds; left out, the session
    file's ``loop.duration_s``, else until Ctrl-C."""
    p.add_argument("--seconds", type=positive_seconds, help="stop after this many seconds, s > 0 (default: the "
                   "session file's loop.duration_s, else run until Ctrl-C)")
    deprecated_alias(p, "--duration", "--seconds")


def overrides_from(args) -> dict:
    from pathlib import Path

    overrides: dict = {}
    if getattr(args, "out", None):
        overrides["out"] = str(Path(args.out).resolve())
    if getattr(args, "record", None):
        overrides["record"] = str(Path(args.record).resolve())
    return overrides


def run(args) -> int:
    from app.session import load_session, run_session

    config = load_session(args.config, overrides_from(args))
    if args.seconds is not None:
        config.loop.duration_s = args.seconds
    if getattr(args, "soak", False):
        config.outputs, config.record, config.out = [], None, None
        for spec in (config.camera, config.robot):
            if spec.name in ("simulated", "recorded"):
                spec.params["loop"] = True
    prepare_session_dirs(config, args.overwrite)
    with naming_the_session_file(args.config):
        result = run_session(config, progress=_progress_printer())
    print_summary(result.summary)
    return recording_exit_code(result.summary)


def recording_problem(summary: dict) -> str | None:
    """Why the session's recording is not complete (plugins/recorder.py), or None (complete, or none)."""
    report = (summary.get("outputs") or {}).get("Recorder")
    if report is None:
        return None
    if "dropped" not in report:    # closing the recorder failed
        return f"the recorder failed: {report.get('error')}"
    if report.get("complete", True):
        return None
    d = report["dropped"]
    why = report.get("error") or "the disk fell behind"
    return (f"the recording in {report['dir']} is incomplete: {d['queue']} frames dropped in the recorder queue and "
            f"{d['disk']} not written, {report.get('joint_samples_lost', 0)} joint samples lost ({why}); it keeps its "
            f".recording-in-progress marker")


def recording_exit_code(summary: dict) -> int:
    """0, or 1 with a line on stderr per problem when the session's recording lost frames or failed,
    or another output (a rerun file on a full disk) could not be completed."""
    import sys

    problems = [recording_problem(summary)] + [
        f"the output {name} is incomplete: {report['error']}" for name, report in (summary.get("outputs") or {}).items()
        if name != "Recorder" and isinstance(report, dict) and set(report) == {"error"}]
    problems = [p for p in problems if p]
    for problem in problems:
        print(f"error: {problem}", file=sys.stderr)
    return 1 if problems else 0


def prepare_session_dirs(config, overwrite: bool) -> None:
    """The overwrite policy (app/commands/outdir.py) for the session's out and record directories
    and its rerun outputs' files; a record folder inside out is listed in out's manifest as a
    folder of its own. The recorded sources' trials are inputs, never outputs."""
    inputs = [spec.params.get("trial") for spec in (config.camera, config.robot)
              if isinstance(spec.params.get("trial"), str)]
    if config.out is not None:
        prepare_dir(config.out, overwrite, "out", inputs)
    if config.record is not None:
        prepare_dir(config.record, overwrite, "record", inputs)
    for i, spec in enumerate(config.outputs):
        path = spec.params.get("path") if spec.name == "rerun" else None
        if isinstance(path, str):
            prepare_file(path, overwrite, f"outputs[{i}].params.path", inputs)


class naming_the_session_file:
    """Context manager: a ConfigError raised while the session runs names the session file."""

    def __init__(self, path):
        self.path = str(path)

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        from app.errors import ConfigError

        if isinstance(exc, ConfigError) and self.path not in str(exc):
            message = str(exc).split(f"config key '{exc.key}': ", 1)[-1]
            raise ConfigError(exc.key, message, self.path) from None
        return False


def _progress_printer():
    import sys
    import time

    last = [0.0]

    def progress(est) -> None:
        now = time.monotonic()
        if now - last[0] >= 1.0:
            last[0] = now
            latency = f"{1e3 * est.latency_s:.0f} ms" if est.latency_s is not None else "-"
            print(f"frame {est.frame_id}: {est.status:9s} latency {latency}", file=sys.stderr)

    return progress


def print_summary(summary: dict, tracked: bool = True) -> None:
    """The session summary; ``tracked=False`` (record without --track): no tracker counts or statuses."""
    lat = summary.get("latency_ms", {})
    frames = summary.get("frames", {})
    counts = (f", {summary.get('processed', 0)} tracked, {summary.get('frames_skipped_by_tracker', 0)} skipped by "
              f"the tracker") if tracked else " (recorded, not tracked)"
    print(f"session: {summary.get('seconds', 0):.1f} s, {frames.get('frames_accepted', 0)} frames accepted{counts}")
    if lat.get("n"):
        print(f"latency frame->estimate: median {lat['median']:.1f} ms, p99 {lat['p99']:.1f} ms, max {lat['max']:.1f} ms")
        first, last = summary.get("latency_first_ms") or {}, summary.get("latency_last_ms") or {}
        if first.get("n") and last.get("n"):
            window = summary.get("latency_window_s", 10)
            print(f"latency p99 over the first {window:.0f} s {first['p99']:.1f} ms, over the last {window:.0f} s "
                  f"{last['p99']:.1f} ms")
        gap = summary.get("estimate_gap_ms") or {}
        if gap.get("n"):
            print(f"time between estimates: median {gap['median']:.1f} ms, p99 {gap['p99']:.1f} ms, "
                  f"max {gap['max']:.1f} ms")
        stages = summary.get("latency_stages_ms") or {}
        if stages:
            print("where the time goes (median / p99 ms): " + ", ".join(
                f"{k.replace('_', ' ')} {v['median']:.1f} / {v['p99']:.1f}" for k, v in stages.items() if v.get("n")))
        print(f"frames dropped: {summary.get('frames_skipped_by_camera', 0)} by the camera (due while it was behind), "
              f"{summary.get('frames_skipped_by_tracker', 0)} in the tracker queue (newer frame waiting)")
    if tracked and summary.get("status_counts"):
        print("status: " + ", ".join(f"{k} {v}" for k, v in sorted(summary["status_counts"].items())))
    if tracked and summary.get("start"):
        from app.pipeline.report import start_text

        print(f"start: {start_text(summary['start'])}")
    if summary.get("events"):
        print("events: " + ", ".join(f"{k} x{v}" for k, v in sorted(summary["events"].items())))
    rss, rate = summary.get("rss_mb") or {}, summary.get("rate_hz") or {}
    if rss.get("start") is not None and rss.get("end") is not None:
        samples = [v for v in rss.get("every_10s") or [] if v is not None]
        half = samples[len(samples) // 2:]
        slope = f", {6 * (half[-1] - half[0]) / (len(half) - 1):+.1f} MB/min over the second half" if len(half) > 2 else ""
        print(f"memory (RSS): {rss['start']:.0f} MB when the sources started, {rss['end']:.0f} MB at the end{slope}")
    if rate.get("all"):
        print(f"tracked frames/s: {rate['all']:.1f} overall, {rate['first']:.1f} in the first and {rate['last']:.1f} "
              f"in the last {summary.get('latency_window_s', 10):.0f} s")
    recorder = (summary.get("outputs") or {}).get("Recorder") or {}
    if isinstance(recorder.get("dropped"), dict):
        d = recorder["dropped"]
        print(f"recorded: {recorder.get('frames', 0)} frames; dropped {d['camera']} by the camera (gaps in its frame "
              f"ids), {d['queue']} in the recorder queue (the disk fell behind), {d['disk']} not written"
              f"{' (' + recorder['error'] + ')' if recorder.get('error') else ''}")
    for name, report in (summary.get("outputs") or {}).items():
        print(f"{name}: {report}")
