"""``osteonav bench``: every configuration on every trial, side by side, with the field's metrics.

Usage::

    from app.bench import bench
    configs = bench.resolve_configs(["A_cpu", "icp", "my_tuned.yaml"])      # built-in names or files
    trials = bench.standard_trials(cache="recordings/bench", seconds=3.0)   # or bench.recorded_trials(dirs)
    rows = bench.run_bench(configs, trials, jobs=1)
    print(bench.table(rows)); bench.write_json(rows, "bench.json"); bench.plot(rows, "plots/")

**Configurations** are YAML files (built-in ones in ``configs/bench/``, copy and edit them). A
particle-filter file is an ordinary tracker configuration (:func:`app.config.load_config`); it may
say ``tracker: particle_filter`` on top. An ICP file says ``tracker: icp`` and has an ``icp``
section with the fields of :class:`app.baselines.icp.ICPParams` (:func:`load_icp_params`).

**Trials**: ``--trials DIR...`` (recorded or simulated trials with ``groundtruth.txt``) or, by
default, the standard scenarios (:data:`app.sim.scenarios.STANDARD`) simulated for the default
mesh and for each ``crest_*.ply`` of ``../shared/data/pelvis`` (skipped when absent), cached in
``recordings/bench/<mesh>/<scenario>`` and re-simulated only when the scenario, its duration, the
seed, the mesh or the depth sensor model changed. ``sensors`` (``--sensors``) simulates each trial with
each model of :mod:`app.sim.sensors`; a model other than ``independent`` is cached in
``<scenario>[_seedN]@<model>`` and named ``<scenario>@<model>`` in the tables (rows carry ``sensor``).

**Columns** (per configuration x trial; errors are of the estimate in the robot base frame
against ``groundtruth.txt``, on every processed frame, whatever the status):

- ``fps``: processed frames per second of wall time of the whole replay loop (PNG decoding, the
  tracker, the per-frame ADD) on this machine; with ``--jobs`` > 1 runs share the CPU.
- ``ADD med / p95`` (mm), ``rot med / p95`` (deg): :mod:`app.metrics`; ADD-S, MDD-S, the
  translation error and VSD are in the JSON, VSD recall in the table.
- ``VSD rec``: fraction of frames with e_VSD < 0.3 (tau = 20 mm), the model rendered at
  :data:`VSD_RESOLUTION` at the estimate and the truth against the measured depth.
- ``lost %``: frames with ADD > 10 mm (the track is gone, whatever the status says).
- ``ok %``: frames whose status is ``ok``.
- ``danger``: frames with status ``ok`` while ADD > 5 mm: the confident wrong pose, which must be 0.
- ``jitter`` (mm / deg): while the bone is static, the RMS of the estimate's frame-to-frame
  change ``|t_k - t_{k-1}|`` and ``angle(R_{k-1}^T R_k)`` over consecutive frame pairs whose
  ground-truth poses are equal (within 1 um / 1e-5 rad), after the first :data:`JITTER_SETTLE_S`
  s (the initial convergence is not jitter). The truth does not move, so any change is jitter.
"""
from __future__ import annotations

from app.bench.configs import (BUILTIN_DIR, BUILTIN_ORDER, REPO, TRACKERS, BenchConfig, builtin_configs,
                               load_bench_config, load_icp_params, resolve_configs)
from app.bench.parallel import pmap
from app.bench.report import COLUMNS, SUMMARY_COLUMNS, plot, summary, summary_table, table, write_json
from app.bench.runs import run_bench, run_one
from app.bench.scoring import (JITTER_SETTLE_S, REST_DELAY_S, after_rest, STATIC_ROTATION_RAD, STATIC_TRANSLATION_M, VSD_RESOLUTION, jitter,
                               static_pairs, vsd_series, in_view_share, refound)
from app.bench.trials import (DEFAULT_CACHE, PELVIS_DIR, QUICK_CONFIGS, QUICK_SCENARIOS, QUICK_STATIC_S, TrialSpec,
                              parse_sensors, pelvis_crest_meshes, quick_seconds, recorded_trials, standard_trials)
from app.metrics import DANGEROUS_ADD_MM, LOST_ADD_MM

__all__ = ["BUILTIN_DIR", "BUILTIN_ORDER", "REPO", "TRACKERS", "BenchConfig", "builtin_configs", "load_bench_config",
           "load_icp_params", "resolve_configs", "pmap", "COLUMNS", "SUMMARY_COLUMNS", "summary", "summary_table", "plot", "table", "write_json", "run_bench",
           "run_one", "JITTER_SETTLE_S", "STATIC_ROTATION_RAD", "STATIC_TRANSLATION_M", "VSD_RESOLUTION", "jitter",
           "static_pairs", "vsd_series", "REST_DELAY_S", "after_rest", "in_view_share", "refound", "DEFAULT_CACHE", "PELVIS_DIR", "QUICK_CONFIGS", "QUICK_SCENARIOS",
           "QUICK_STATIC_S", "TrialSpec", "parse_sensors", "pelvis_crest_meshes", "quick_seconds", "recorded_trials",
           "standard_trials", "DANGEROUS_ADD_MM", "LOST_ADD_MM"]
