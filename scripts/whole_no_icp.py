"""`osteonav bench-rate --whole` without the Open3D ICP row, for a machine without open3d.

app.bench.whole.measure with app.baselines.icp.ICPTracker replaced by a stub that does nothing, so
the tracker's row (wall and CPU per frame, stage split, statuses) is measured exactly as the command
does; the ICP row and the ratios are meaningless and dropped.

    printf 'render:\n  backend: gl\n' > whole_gl.yaml
    .venv/bin/osteonav simulate --out /tmp/whole_trial --mesh ../shared/data/pelvis/crest_left_02.ply \
        --scenario static_clear --seed 0 --seconds 1
    .venv/bin/python scripts/whole_no_icp.py --config whole_gl.yaml --trial /tmp/whole_trial --frames 60 --json whole_gl.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # the repository's app package


class _NoICP:
    def __init__(self, *a, **k):
        pass

    def start(self, T):
        pass

    def process(self, depth, stamp, pose):
        return SimpleNamespace(status="skipped", refined=False)

    def release(self):
        pass


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", required=True)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--trial", default=None)
    ap.add_argument("--json", required=True)
    args = ap.parse_args()

    import logging

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    import app.baselines.icp as icp
    from app.bench import whole
    from app.bench.trials import DEFAULT_CACHE
    from app.config import load_config

    icp.ICPTracker = _NoICP
    config = load_config(args.config)
    if args.trial:
        trial = Path(args.trial)
    else:
        mesh = whole.default_crest()
        if mesh is None:
            print("no crest mesh found (PELVIS_DIR)", file=sys.stderr)
            return 2
        trial = whole.simulated_trial(mesh, args.seconds, DEFAULT_CACHE)
    result = whole.measure(trial, config, frames=args.frames)
    result.pop("icp", None)
    result.pop("ratio", None)
    result.pop("cpu_ratio", None)
    result["config"] = args.config
    t = result["tracker"]
    print(f"trial {result['trial']} ({result['mesh']}): {t['description']}; {result['frames']} frames after "
          f"{result['warmup']} warm-up")
    print(f"tracker fps {t['fps']:.1f}, frame {t['frame_ms']:.2f} ms, cpu {t['cpu_ms']:.2f} ms/frame, "
          f"statuses {t['status_counts']}, search frames {t['search_frames']}")
    print("stages ms:", {k: round(v, 2) for k, v in t["stages_ms"].items()})
    Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
