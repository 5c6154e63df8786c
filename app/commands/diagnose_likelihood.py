"""``osteonav diagnose-likelihood TRIAL``: the truth against the best other poses, per frame.

For the chosen frames of a trial with ground truth: the tracker's log-likelihood and the
refinement's fit at the ground truth against the best poses a wide search finds more than
5 mm / 5 deg away (:mod:`app.bench.ambiguity`), as a markdown table (printed, and written with a
JSON copy under ``--out``) and a rerun recording of the per-pixel log-likelihood terms at the truth
and at the best other pose (``--out``/diagnosis.rrd).
"""
from __future__ import annotations

from app.cli_types import finite_positive_float, non_negative_int, positive_int, seed
from app.commands.outdir import add_overwrite_argument, prepare_dir


def register(subparsers) -> None:
    p = subparsers.add_parser("diagnose-likelihood", help="log-likelihood and refinement fit at the ground truth "
                              "against the best poses > 5 mm / 5 deg away, per frame")
    p.add_argument("trial", help="trial directory with groundtruth.txt")
    p.add_argument("--frames", type=non_negative_int, nargs="+", default=None,
                   help="frame indices, integers >= 0 (default: 5 spread over the trial)")
    p.add_argument("--config", help="tracker YAML (default: configs/default.yaml's values)")
    p.add_argument("--candidates", type=positive_int, default=2000,
                   help="poses of the wide search per frame, >= 1 (default %(default)s)")
    p.add_argument("--search-mm", type=finite_positive_float, default=40.0,
                   help="translation range of the search, mm > 0 (default %(default)s)")
    p.add_argument("--search-deg", type=finite_positive_float, default=40.0,
                   help="rotation range of the search, deg > 0 (default %(default)s)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the search, an integer >= 0 (default 0)")
    p.add_argument("--out", default=None, help="folder for diagnosis.md / .json / .rrd (default: print only)")
    add_overwrite_argument(p, "--out's diagnosis")
    p.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import asdict
    from pathlib import Path

    import numpy as np

    from app import strict_json
    from app.bench import ambiguity
    from app.outputs import wrote
    from app.config import load_config
    from app.errors import OsteonavError
    from app.trial.reader import open_trial

    config = load_config(args.config)
    reader = open_trial(args.trial)
    if reader.groundtruth is None:
        raise OsteonavError(f"{args.trial}: no groundtruth.txt; diagnose-likelihood compares against the ground truth "
                            "(use a simulated trial)")
    n = len(reader.stamps)
    frames = args.frames if args.frames else list(np.linspace(0, n - 1, 5).astype(int))
    bad = [f for f in frames if not 0 <= f < n]
    if bad:
        raise OsteonavError(f"--frames {bad}: the trial has frames 0..{n - 1}")
    if args.out:
        prepare_dir(args.out, args.overwrite, inputs=[args.trial])
    backend, refiner, camera_small = _scorers(config, reader)
    rrd = _recording(Path(args.out) / "diagnosis.rrd") if args.out else None
    rec = rrd.rec if rrd is not None else None
    rng = np.random.default_rng(args.seed)
    T_base_camera, pose_valid = reader.camera_poses()
    rows = []
    for frame in reader.iter_frames():
        if frame.index not in frames or not pose_valid[frame.index]:
            continue
        from app.depth_image import downsample_nearest
        from app.geometry import se3

        depth_small = downsample_nearest(frame.depth_m, camera_small.width, camera_small.height)
        T_true = se3.inverse(T_base_camera[frame.index]) @ reader.groundtruth[frame.index]
        row, T_other = ambiguity.diagnose_frame(frame.index, backend, refiner, frame.depth_m, depth_small, T_true, rng,
                                                config.particles, args.candidates, args.search_mm, args.search_deg)
        rows.append(row)
        print(f"  frame {frame.index}: LL truth {row.ll_truth:.1f}, best other {row.ll_best:.1f} "
              f"({row.best_mm:.1f} mm / {row.best_deg:.1f} deg)", flush=True)
        if rec is not None:
            _log_terms(rec, backend, config, frame.index, depth_small, T_true, T_other)
    backend.release()
    if rrd is not None:
        rrd.close()   # an OutputError (one line) when the disk was full
    text = ambiguity.table(rows)
    print(text)
    if args.out:
        for name, content in (("diagnosis.md", text + "\n"),
                              ("diagnosis.json", strict_json.dumps([asdict(r) for r in rows], indent=1))):
            wrote(Path(args.out) / name)
            (Path(args.out) / name).write_text(content)
        print(f"\nwrote {args.out}/diagnosis.md, .json, .rrd")
    return 0


def _scorers(config, reader):
    """The tracker's GL likelihood (filter resolution) and refinement (full resolution) for the trial's mesh."""
    import numpy as np

    from app.filter.refine import Refiner
    from app.mesh import prepare_mesh
    from app.pipeline.tracker import refine_params
    from app.render.context import shared_context
    from app.render.likelihood import GLLikelihoodBackend

    mesh = reader.load_mesh()
    tracking = prepare_mesh(mesh, max_triangles=config.mesh_triangles, center=False)
    camera_small = reader.meta.camera.resized(*config.resolution)
    backend = GLLikelihoodBackend(shared_context(), np.asarray(tracking.vertices), np.asarray(tracking.faces),
                                  camera_small, config.particles, config.likelihood, near=config.near, far=config.far)
    params = refine_params(config)
    return backend, Refiner(np.asarray(mesh.vertices), np.asarray(mesh.faces), reader.meta.camera, params), camera_small


def _recording(path):
    """The rerun recording of the terms, written to ``path`` (app/viz/rrd_file.py)."""
    import rerun as rr

    from app.viz.rrd_file import RrdFile

    return RrdFile(rr.RecordingStream("osteonav-diagnose-likelihood"), path)


def _log_terms(rec, backend, config, index, depth_small, T_true, T_other) -> None:
    """Per-pixel log-likelihood terms (app/filter/likelihood_ref.py) at the truth and the best other pose."""
    import numpy as np
    import rerun as rr

    from app.filter.likelihood_ref import pixel_log_likelihood

    rendered = backend.render_depth(np.stack([T_true, T_other]))
    rec.set_time("frame", sequence=int(index))
    for name, z_star in (("truth", rendered[0]), ("best_other", rendered[1])):
        terms = pixel_log_likelihood(depth_small, z_star, config.likelihood).astype(np.float32)
        rec.log(f"terms/{name}", rr.Tensor(terms))
    rec.log("measured", rr.DepthImage(np.round(np.nan_to_num(depth_small) * 1000).astype(np.uint16), meter=1000.0))
