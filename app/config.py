"""Tracker configuration: a YAML file validated into :class:`TrackerConfig`.

Usage::

    from app.config import load_config
    config = load_config("configs/default.yaml")   # or load_config(None) for the defaults

``configs/default.yaml`` documents every key, its unit and where its value comes from. The YAML
has eight sections; each key maps to one attribute:

- ``filter.*``     -> ``config.particles``, ``sampling``, ``resample_threshold``, ``resampling``,
                      ``first_dt``, ``seed``
- ``init.sigma_p`` / ``init.sigma_r`` -> ``config.init_sigma_p`` / ``init_sigma_r``; ``init.method``
  ('auto' | 'pose' | 'point'), ``point_sigma``, ``restarts``, ``budget_s`` -> ``config.init_method`` ... (the
  one-point initialiser, :mod:`app.filter.smc_init`); ``init.detector_*`` -> ``config.detector``
  (:class:`app.tracking.detector.StartSearch`: the start's search)
- ``motion.*``     -> ``config.motion`` (:class:`app.filter.motion.MotionParams`)
- ``likelihood.*`` -> ``config.likelihood`` (:class:`app.filter.likelihood_ref.LikelihoodParams`)
- ``status.*``     -> ``config.status`` (:class:`app.filter.status.StatusThresholds`)
- ``refine.*``     -> ``config.refine`` (:class:`app.filter.refine_track.RefineConfig`)
- ``recovery.*``   -> ``config.recovery`` (:class:`app.filter.recovery.RecoveryConfig`)
- ``render.*``     -> ``config.resolution`` (width, height), ``near``, ``far``,
                      ``mesh_triangles``, ``cull_back_faces``, ``backend``

Keys left out take their defaults. Validation happens here, once (STYLE.md §11): types, ranges,
allowed names and unknown keys (with a "did you mean" suggestion) raise
:class:`app.errors.ConfigError` naming the dotted key, the allowed range or values, and the fix.
Units: metres, seconds, radians.
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from app.errors import ConfigError
from app.filter.likelihood_ref import OCCLUSION_MODELS, LikelihoodParams
from app.filter.motion import MotionParams
from app.filter.observation import BACKENDS
from app.filter.particle_filter import SAMPLING_MODES, FilterConfig
from app.filter.recovery import RecoveryConfig
from app.tracking.detector import StartSearch
from app.filter.refine_track import RefineConfig
from app.filter.resampling import SCHEMES
from app.pipeline.stages import MODES as STAGES

INIT_METHODS = ("auto", "pose", "point")

DEFAULT_CONFIG_PATH = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


@dataclass
class TrackerConfig(FilterConfig):
    """Everything the depth tracker needs: the filter's settings plus the renderer's.

    resolution : (width, height) px of the filter's images ((A)/(B): 80x60)
    near, far : m, clip planes of the batched renderer
    mesh_triangles : triangle budget of the decimated tracking mesh
    cull_back_faces : cull back faces when the mesh is consistently wound outwards
    backend : likelihood backend, 'auto' (cpu on a software GL renderer such as llvmpipe, gl on a
        GPU), 'gl' or 'cpu' (app/render/backends.py)
    seed : seed of the filter's np.random.Generator (a replay with one seed is reproducible)
    stages : 'auto' (the default: parallel on two or more cores with the refinement on, else serial),
        'serial' or 'parallel': the refinement's work that needs nothing of the filter's frame runs on a
        second thread beside the filter's step, with the same results (app/pipeline/stages.py; measured
        1.11-1.12x serial's frames/s on the idle 2-core sandbox, BENCHMARKS.md "Filter rate and CPU")
    init_method : 'auto' (the default: the coarse initial pose when there is one, else the point prior
        through the detector, app/tracking/detector.py: the wide search around the point, verified by the
        refinement, ok only once confirmed; else, experimentally, the detector over the whole image),
        'pose' (particles around the coarse initial pose) or 'point' (the one-point SMC initialiser of
        DESIGN.md on the first frame, from a point on the bone, app/filter/smc_init/; never ok)
    init_point_sigma : m, σ_t, how far the pointed point may lie off the bone's surface
    init_restarts, init_budget_s : independent runs of the initialiser (the most likely kept), and
        a wall-time safety net only (s; the budget is counted in likelihood evaluations, smc_init.py)
    detector : the detector's search for a start from a point or from nothing
        (:class:`app.tracking.detector.StartSearch`: ``init.detector_*``)
    refine : the local refinement and its own track (app/filter/refine_track.py)
    recovery : the automatic re-initialisation of a lost track (app/filter/recovery.py)

    The product's defaults differ from the publications' in four measured places (BENCHMARKS.md,
    "Choosing the defaults"): the background-ratio likelihood with tempering α = 0.2 (the plain
    beam model drifts away from a hand over the bone: 25 % of the frames lost vs 1 %), and
    slower motion noise σ_a = 2 m/s², σ_α = 20 rad/s² (less jitter at 200 particles, and it kept
    up with the 25 cm/s repositioning where (A)'s 5 / 50 lost the bone), and 160x120 px images
    (ADD median 0.81 vs 1.12 mm, rotation 1.33 vs 1.80 deg on the demo trial, for about 25 % more
    time per frame on llvmpipe, where rendering the triangles dominates). ``configs/bench`` has the
    publications' own settings.
    """

    resolution: tuple[int, int] = (160, 120)
    near: float = 0.05
    far: float = 4.0
    mesh_triangles: int = 1000
    cull_back_faces: bool = True
    backend: str = "auto"
    seed: int = 0
    stages: str = "auto"
    init_method: str = "auto"
    init_point_sigma: float = 0.005
    init_restarts: int = 3
    init_budget_s: float = 600.0
    detector: StartSearch = field(default_factory=StartSearch)
    motion: MotionParams = field(default_factory=lambda: MotionParams(sigma_a=2.0, sigma_alpha=20.0))
    likelihood: LikelihoodParams = field(default_factory=lambda: LikelihoodParams(background_ratio=True,
                                                                                  pixel_weight=0.2))
    refine: RefineConfig = field(default_factory=RefineConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)

    def __post_init__(self):
        """Values that one key decides in several places (issue 32: toward 15 decision numbers), set here so
        that no caller can hold them apart:

        - one patience with a track that is not ok: a frame without a camera pose is lost after
          ``recovery.after_uncertain_s`` without one (the status' ``lost_no_pose_s``, a key of its own until
          then: 0.5 s, our choice, not measured). 0 (the triggers off) makes such a frame lost at once;
        - one distance between two answers: the particles' cloud spread over the template's points by more
          than ``refine.competitor_distance`` holds no one answer and is lost (the status' ``lost_spread``,
          a key of its own until then: 10 mm, the replay's definition of a lost frame);
        - one settling time: a wide search that found nothing (or a start's detector) is tried again after
          ``status.settle_s``, the time the motion test gives a bone to settle (the recovery's
          ``search_retry_s``, a key of its own until then: 0.33 s, 30 frames at 90 Hz)."""
        tied = {"lost_no_pose_s": self.recovery.after_uncertain_s, "lost_spread": self.refine.competitor_distance}
        if any(getattr(self.status, name) != value for name, value in tied.items()):
            self.status = replace(self.status, **tied)
        if self.recovery.search_retry_s != self.status.settle_s:
            self.recovery = replace(self.recovery, search_retry_s=self.status.settle_s)


@dataclass(frozen=True)
class _Key:
    """One YAML key: its attribute path in TrackerConfig, its kind and its allowed range/values."""

    path: tuple[str, ...]
    kind: str  # 'int' | 'float' | 'bool' | 'choice' | 'resolution'
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[str, ...] = ()


def _f(path, lo=None, hi=None, lo_open=False):
    return _Key(tuple(path.split(".")), "float", lo, hi, lo_open)


def _i(path, lo=None, hi=None):
    return _Key(tuple(path.split(".")), "int", lo, hi)


KEYS: dict[str, _Key] = {
    "filter.particles": _i("particles", 1, 100_000),
    "filter.sampling": _Key(("sampling",), "choice", choices=SAMPLING_MODES),
    "filter.resample_threshold": _f("resample_threshold", 0.0, 1.0),
    "filter.resampling": _Key(("resampling",), "choice", choices=tuple(sorted(SCHEMES))),
    "filter.first_dt": _f("first_dt", 0.0, 1.0, lo_open=True),
    "filter.seed": _i("seed", 0, 2**63 - 1),
    "filter.stages": _Key(("stages",), "choice", choices=STAGES),
    "init.sigma_p": _f("init_sigma_p", 0.0, 0.5),
    "init.sigma_r": _f("init_sigma_r", 0.0, math.pi),
    "init.method": _Key(("init_method",), "choice", choices=INIT_METHODS),
    "init.point_sigma": _f("init_point_sigma", 0.0, 0.1, lo_open=True),
    "init.restarts": _i("init_restarts", 1, 100),
    "init.budget_s": _f("init_budget_s", 0.0, 3600.0, lo_open=True),
    "init.detector_evaluations": _i("detector.evaluations", 100, 10_000_000),
    "init.detector_clusters": _i("detector.clusters", 1, 1000),
    "init.detector_verified": _i("detector.refine_top", 1, 1000),
    "init.detector_tilt": _f("detector.tilt_rad", 0.0, math.pi / 2),
    "init.detector_tilt_directions": _i("detector.tilt_directions", 0, 64),
    "init.detector_screened": _i("detector.screened", 0, 100_000),
    "init.detector_chains": _Key(("detector", "chains"), "choice", choices=("wide", "both")),
    "motion.sigma_a": _f("motion.sigma_a", 0.0, 1000.0),
    "motion.sigma_alpha": _f("motion.sigma_alpha", 0.0, 10_000.0),
    "motion.lambda_v": _f("motion.lambda_v", 0.0, 1.0),
    "likelihood.z_max": _f("likelihood.z_max", 0.0, 20.0, lo_open=True),
    "likelihood.lam": _f("likelihood.lam", 0.0, 100.0, lo_open=True),
    "likelihood.w_u": _f("likelihood.w_u", 0.0, 1.0),
    "likelihood.w_e": _f("likelihood.w_e", 0.0, 1.0),
    "likelihood.w_n": _f("likelihood.w_n", 0.0, 1.0),
    "likelihood.k": _f("likelihood.k", 0.0, 1.0),
    "likelihood.sigma_base": _f("likelihood.sigma_base", 0.0, 0.1, lo_open=True),
    "likelihood.occlusion": _Key(("likelihood", "occlusion"), "choice", choices=OCCLUSION_MODELS),
    "likelihood.classification": _Key(("likelihood", "classification"), "bool"),
    "likelihood.l0_weight": _f("likelihood.l0_weight", 0.0, 1000.0),
    "likelihood.pixel_count_reg": _f("likelihood.pixel_count_reg", 0.0, 1e6),
    "likelihood.background_ratio": _Key(("likelihood", "background_ratio"), "bool"),
    "likelihood.pixel_weight": _f("likelihood.pixel_weight", 0.0, 1.0, lo_open=True),
    "likelihood.occluder_margin": _f("likelihood.occluder_margin", 0.0, 1.0, lo_open=True),
    "status.lost_inlier_fraction": _f("status.lost_inlier_fraction", 0.0, 1.0),
    "status.min_covered_pixels": _i("status.min_covered_pixels", 0, 10_000_000),
    "status.uncertain_speed": _f("status.uncertain_speed", 0.0, 100.0, lo_open=True),
    "status.motion_window_s": _f("status.motion_window_s", 0.0, 10.0, lo_open=True),
    "status.settle_s": _f("status.settle_s", 0.0, 60.0),
    "status.min_fitness": _f("status.min_fitness", 0.0, 1.0),
    "status.max_template_std": _f("status.max_template_std", 0.0, 1.0, lo_open=True),
    "status.alpha": _f("status.alpha", 0.0, 0.5, lo_open=True),
    "status.max_behind_excess": _f("status.max_behind_excess", 0.0, 1.0),
    "status.covariance_inflation": _f("status.covariance_inflation", 1.0, 1e6),
    "refine.enabled": _Key(("refine", "enabled"), "bool"),
    "refine.stride": _i("refine.stride", 1, 8),
    "refine.iterations": _i("refine.iterations", 0, 50),
    "refine.samples": _i("refine.samples", 1000, 1_000_000),
    "refine.keep_fitness": _f("refine.keep_fitness", 0.0, 1.0),
    "refine.reseed_fitness": _f("refine.reseed_fitness", 0.0, 1.0),
    "refine.competitor_distance": _f("refine.competitor_distance", 0.0, 1.0),
    "refine.feedback": _Key(("refine", "feedback"), "bool"),
    "refine.feedback_spread": _f("refine.feedback_spread", 0.0, 1.0, lo_open=True),
    "refine.feedback_spread_angle": _f("refine.feedback_spread_angle", 0.0, math.pi, lo_open=True),
    "refine.static_prior": _Key(("refine", "static_prior"), "bool"),
    "refine.prior_release_chi2": _f("refine.prior_release_chi2", 0.0, 1e6, lo_open=True),
    "refine.prior_clear_ratio": _f("refine.prior_clear_ratio", 1.0, 1e6),
    "refine.prior_information_frames": _f("refine.prior_information_frames", 1.0, 1e6),
    "refine.prior_motion_frames": _i("refine.prior_motion_frames", 0, 100_000),
    "refine.prior_forget_ratio": _f("refine.prior_forget_ratio", 0.0, 1e6),
    "refine.seed_starts": _i("refine.seed_starts", 0, 10_000),
    "refine.seed_spread": _f("refine.seed_spread", 0.0, 10.0),
    "refine.outline_ring": _Key(("refine", "outline_ring"), "bool"),
    "refine.tissue_border": _Key(("refine", "tissue_border"), "bool"),
    "refine.behind_frames": _i("refine.behind_frames", 1, 100_000),
    "refine.noise_window_px": _i("refine.noise_window_px", 3, 1000),
    "refine.nearby_every": _i("refine.nearby_every", 0, 100_000),
    "refine.nearby_starts": _i("refine.nearby_starts", 0, 1_000),
    "refine.nearby_sigma_p": _f("refine.nearby_sigma_p", 0.0, 0.05, lo_open=True),
    "refine.nearby_sigma_r": _f("refine.nearby_sigma_r", 0.0, math.pi, lo_open=True),
    "refine.nearby_margin": _f("refine.nearby_margin", 0.0, 1.0),
    "refine.nearby_hold": _i("refine.nearby_hold", 1, 100_000),
    "refine.nearby_validate": _Key(("refine", "nearby_validate"), "bool"),
    "refine.nearby_per_frame": _i("refine.nearby_per_frame", 0, 1_000),
    "recovery.enabled": _Key(("recovery", "enabled"), "bool"),
    "recovery.after_lost_s": _f("recovery.after_lost_s", 0.0, 3600.0, lo_open=True),
    "recovery.after_uncertain_s": _f("recovery.after_uncertain_s", 0.0, 3600.0),
    "recovery.respread_sigma_p": _f("recovery.respread_sigma_p", 0.0, 0.2, lo_open=True),
    "recovery.respread_sigma_r": _f("recovery.respread_sigma_r", 0.0, math.pi, lo_open=True),
    "recovery.respreads": _i("recovery.respreads", 0, 100),
    "recovery.smc_evaluations": _i("recovery.smc_evaluations", 600, 10_000_000),
    "recovery.confirm_frames": _i("recovery.confirm_frames", 0, 1_000_000),
    "recovery.search": _Key(("recovery", "search"), "bool"),
    "recovery.search_evaluations": _i("recovery.search_evaluations", 100, 10_000_000),
    "recovery.sliding_factor": _f("recovery.sliding_factor", 1.0, 1000.0),
    "recovery.still_window_s": _f("recovery.still_window_s", 0.0, 60.0),
    "recovery.confirm_moved": _Key(("recovery", "confirm_moved"), "bool"),
    "recovery.search_worker": _Key(("recovery", "search_worker"), "choice", choices=("auto", "inline", "thread", "process")),
    "render.resolution": _Key(("resolution",), "resolution", 8, 4096),
    "render.near": _f("near", 0.0, 10.0, lo_open=True),
    "render.far": _f("far", 0.0, 100.0, lo_open=True),
    "render.mesh_triangles": _i("mesh_triangles", 4, 10_000_000),
    "render.cull_back_faces": _Key(("cull_back_faces",), "bool"),
    "render.backend": _Key(("backend",), "choice", choices=BACKENDS),
}
SECTIONS = tuple(dict.fromkeys(k.split(".")[0] for k in KEYS))


def load_config(path: str | Path | None = None) -> TrackerConfig:
    """TrackerConfig from a YAML file, or the defaults when ``path`` is None.

    Raises ConfigError for a missing or unparsable file and for any invalid key (module docstring).
    """
    if path is None:
        return TrackerConfig()
    path = Path(path)
    if not path.is_file():
        raise ConfigError("(file)", f"no such configuration file; pass an existing YAML file, "
                          f"e.g. {DEFAULT_CONFIG_PATH}", source=str(path))
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError("(file)", f"not valid YAML: {exc}", source=str(path)) from None
    return config_from_dict(data or {}, source=str(path))


def config_from_dict(data: Any, source: str | None = None) -> TrackerConfig:
    """Validate a parsed YAML mapping ({section: {key: value}}) into a TrackerConfig."""
    if not isinstance(data, dict):
        raise ConfigError("(top level)", f"expected a mapping of sections ({', '.join(SECTIONS)}), "
                          f"got {type(data).__name__}", source)
    config = TrackerConfig()
    for section, values in data.items():
        if section not in SECTIONS:
            raise ConfigError(str(section), f"unknown section{_suggest(str(section), SECTIONS)}; "
                              f"valid sections: {', '.join(SECTIONS)}", source)
        if values is None:
            continue
        if not isinstance(values, dict):
            raise ConfigError(section, f"expected a mapping of keys, got {type(values).__name__} {values!r}", source)
        for name, value in values.items():
            key = f"{section}.{name}"
            if key in RENAMED:
                raise ConfigError(key, RENAMED[key], source)
            if key not in KEYS:
                raise ConfigError(key, f"unknown key{_suggest_key(key)}; valid keys of '{section}': "
                                  f"{', '.join(k.split('.', 1)[1] for k in KEYS if k.startswith(section + '.'))}",
                                  source)
            config = _set(config, KEYS[key].path, _check(key, KEYS[key], value, source))
    _check_consistency(config, source)
    return config


def config_to_dict(config: TrackerConfig) -> dict:
    """The YAML mapping of a TrackerConfig ({section: {key: value}}), e.g. for a run's summary."""
    out: dict[str, dict] = {}
    for key, spec in KEYS.items():
        section, name = key.split(".", 1)
        value = config
        for attr in spec.path:
            value = getattr(value, attr)
        out.setdefault(section, {})[name] = list(value) if spec.kind == "resolution" else value
    return out


def _set(obj, path: tuple[str, ...], value):
    if len(path) == 1:
        return replace(obj, **{path[0]: value})
    return replace(obj, **{path[0]: _set(getattr(obj, path[0]), path[1:], value)})


def _range_text(spec: _Key) -> str:
    lo = "(" if spec.lo_open else "["
    return f"{lo}{spec.lo:g}, {spec.hi:g}]"


def _check(key: str, spec: _Key, value, source):
    if spec.kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(key, f"expected true or false, got {value!r}", source)
        return value
    if spec.kind == "choice":
        if not isinstance(value, str) or value not in spec.choices:
            hint = _suggest(str(value), spec.choices)
            raise ConfigError(key, f"{value!r} is not one of: {', '.join(spec.choices)}{hint}", source)
        return value
    if spec.kind == "resolution":
        ok = (isinstance(value, (list, tuple)) and len(value) == 2
              and all(isinstance(v, int) and not isinstance(v, bool) and spec.lo <= v <= spec.hi for v in value))
        if not ok:
            raise ConfigError(key, f"expected [width, height], two integers in [{spec.lo:g}, {spec.hi:g}] "
                              f"(e.g. [80, 60]), got {value!r}", source)
        return (int(value[0]), int(value[1]))
    if spec.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer in [{spec.lo:g}, {spec.hi:g}], got {value!r}", source)
    elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(key, f"expected a finite number in {_range_text(spec)}, got {value!r}", source)
    too_low = value <= spec.lo if spec.lo_open else value < spec.lo
    if too_low or value > spec.hi:
        raise ConfigError(key, f"{value!r} is outside the allowed range {_range_text(spec)}", source)
    return int(value) if spec.kind == "int" else float(value)


def _check_consistency(c: TrackerConfig, source) -> None:
    lk = c.likelihood
    if lk.w_u + lk.w_e + lk.w_n <= 0:
        raise ConfigError("likelihood.w_n", "the mixture weights w_u + w_e + w_n must be positive "
                          "(DESIGN.md: e.g. 0.05, 0.15, 0.8)", source)
    if c.far <= c.near:
        raise ConfigError("render.far", f"far ({c.far:g} m) must exceed near ({c.near:g} m)", source)
    st = c.status
    forget = c.refine.prior_forget_ratio
    if 0.0 < forget <= 1.0:
        raise ConfigError("refine.prior_forget_ratio", f"{forget:g} would discount the prior on a view no better "
                          "than the one that built it; use a ratio above 1 (e.g. 2.0) or 0 to disable", source)


RENAMED = {   # keys of earlier configurations: what replaced them
    "recovery.after_lost_frames": "replaced by recovery.after_lost_s, in seconds (counted in processed frames "
                                  "whatever their rate; app/filter/recovery.py): frames / 90 at 90 Hz, e.g. 10 -> 0.11",
    "recovery.after_uncertain_frames": "replaced by recovery.after_uncertain_s, in seconds (counted in processed "
                                       "frames whatever their rate): frames / 90 at 90 Hz, e.g. 90 -> 1.0; 0 = off",
    "recovery.cooldown_frames": "replaced by recovery.after_lost_s, in seconds (counted in processed frames whatever "
                                "their rate): frames / 90 at 90 Hz, e.g. 10 -> 0.11 (the cooldown's base since issue 32)",
    "recovery.cooldown_s": "replaced by recovery.after_lost_s (issue 32: one reaction time; the wait between two "
                           "re-initialisations, doubled per attempt, starts at the bad frames' 0.11 s instead of "
                           "0.16 s; the recovery matrix found every bone within 2 s); remove the key",
    # issue 32: exact duplicates merged (same value, same meaning; replays byte-identical, BENCHMARKS.md)
    "recovery.far_m": "replaced by refine.competitor_distance (the same 5 mm: two poses this far apart are different "
                      "answers, for the competitor rule and for the recovery's \"far from the last ok pose\"); "
                      "move its value there",
    "recovery.far_angle": "replaced by refine.competitor_distance (the template's largest displacement; it was 5 deg, for the competitor rule and the "
                          "recovery's \"far\"); move its value there",
    "recovery.never_ok_search_s": "replaced by recovery.after_uncertain_s (the same 1 s of still, not-ok frames: a "
                                  "never-ok track's one search waits as long as the slow trigger); remove the key",
    "refine.nearby_gap": "replaced by status.max_template_std (the same 1 mm clinical tolerance: a nearby fit moving "
                         "the template by more is a different answer); move its value there",
    "refine.feedback_fitness": "replaced by status.min_fitness (the same 0.6: only a fit confirming the share ok "
                               "needs shifts the particle cloud); move its value there",
    # issue 32: the filter's shares fitted to one simulator, off with the refinement (the default; replays
    # byte-identical, BENCHMARKS.md): ok needs the refinement's tests, and without it no frame is ok
    "status.uncertain_inlier_fraction": "replaced by the refinement's consistency test (status.max_behind_excess, "
                                        "at the noise measured in the image); without the refinement "
                                        "(refine.enabled: false) no frame is ok; remove the key",
    "status.min_ok_fraction": "replaced by status.max_template_std (the template's predicted error says when too "
                              "little of the bone is seen); without the refinement no frame is ok; remove the key",
    "status.min_ess_ratio": "replaced by status.max_template_std (the rule was off: a small ESS is normal with "
                            "peaked likelihoods); remove the key",
    # issue 32: one level for the statistical tests (app/tracking/levels.py)
    "refine.behind_z": "replaced by status.alpha, the one level of every statistical test: z = -Phi^-1(alpha) "
                       "(alpha 0.00135 gives 3 sd); set status.alpha = Phi(-z) instead",
    "status.max_held_chi2": "replaced by status.alpha, the one level of every statistical test: the bound is "
                            "chi2_6(1 - alpha) / status.covariance_inflation (3.62 at the default alpha; 4 was "
                            "alpha ~5e-4)",
    "recovery.start_sigmas": "replaced by status.alpha, the one level of every statistical test: k^2 = "
                             "chi2_3(1 - alpha) (3.95 at the default alpha; 4.03 was alpha 0.001)",
    # issue 32: the particles' spread no longer lowers the status below the lost one (the template's predicted error
    # says how precise the refined output is); it still gates the feedback
    "status.uncertain_position_spread": "replaced by status.max_template_std for the status (the template's predicted "
                                        "error); the feedback's wait for a converged cloud is refine.feedback_spread "
                                        "(the same 3 mm); move its value there",
    "status.uncertain_rotation_spread": "replaced by status.max_template_std for the status; the feedback's wait for a "
                                        "converged cloud is refine.feedback_spread_angle (the same 2 deg); move its "
                                        "value there",
    # issue 32: one motion test, on the template's points
    "status.uncertain_angular_speed": "replaced by status.uncertain_speed, now the largest speed of the template's "
                                      "points (a turn of 20 deg/s moves points 85 mm out at 30 mm/s); remove the key",
    # issue 32: the hold after a re-initialisation is the motion test's settle (the estimate jumped)
    "recovery.hold_frames": "replaced by status.settle_s: after a re-initialisation the tracker restarts its motion "
                            "test, and the status stays below ok for settle_s (0.3 s, 27 frames at 90 Hz; the hold "
                            "was 15 weighed frames); remove the key",
    # issue 32: one tolerance for "a different answer"
    "recovery.kept_move_m": "replaced by status.max_template_std (the same 1 mm, now the largest displacement of the "
                            "template's points between the kept and the refined pose); remove the key",
    # issue 32: toward 15 decision numbers (BENCHMARKS.md "Decision numbers")
    "recovery.min_visible_share": "replaced by status.min_fitness (the same 0.6): a due re-initialisation waits until "
                                  "that share of the bone's expected silhouette is not hidden, since a pose found on "
                                  "less could never be ok; remove the key",
    "recovery.max_backoff_doublings": "replaced by recovery.after_uncertain_s as the backoff's cap: after attempt k the "
                                      "next waits min(cooldown_s 2^k, after_uncertain_s) (0.16 s up to 1 s; it was up "
                                      "to 8x, 1.28 s); remove the key",
    "status.lost_position_spread": "replaced by status.lost_spread, the template's points' spread over the particles "
                                    "(the same 10 mm, now of the template, not the bone frame's origin); move its value there",
    "status.lost_rotation_spread": "replaced by status.lost_spread (the template's points' spread covers the rotation: "
                                   "10 deg moves points 60 mm out 10 mm); remove the key",
    "refine.competitor_angle": "replaced by refine.competitor_distance, now the template's largest displacement "
                               "between two poses (5 mm; 5 deg moves points 60 mm out 5 mm); remove the key",
    "refine.competitor_margin": "replaced by refine.nearby_margin (issue 32: one margin within which two fits' "
                                "shares are not told apart, x sqrt(f) for correlated noise; 0.05 against 0.015 "
                                "changed none of 48 status runs); remove the key",
    "refine.nearby_followups": "removed (issue 32): the nearby search no longer searches again about a better fit "
                               "within the tolerance; its scene (crest_left_02 or_model_mismatch) is never ok while "
                               "> 1 mm off without it, and the status and recovery matrices kept every run's safety; "
                               "remove the key",
    "recovery.search_min_sharp": "replaced by status.min_fitness (issue 32: the search's bar on a fit's share within "
                                 "1 sigma is the fitness bar's share at 1 sigma for Gaussian residuals, "
                                 "0.6 x 0.683 / 0.997 = 0.411, app/tracking/levels.py sharp_bar; it was 0.5); remove the key",
    "recovery.search_retry_s": "replaced by status.settle_s (issue 32: one settling time): a wide search that found "
                               "nothing, or a start's detector, is tried again after the time the motion test gives a "
                               "bone to settle (0.3 s; it was 0.33 s); remove the key",
    "status.lost_spread": "replaced by refine.competitor_distance (issue 32: one distance between two answers): the "
                          "particles spread over the template's points by more than that (5 mm; it was 10 mm) hold "
                          "no one answer and the frame is lost; remove the key",
    "status.lost_no_pose_s": "replaced by recovery.after_uncertain_s (issue 32: one patience with a track that is "
                             "not ok): a frame without a camera pose is lost after that long without one (1 s; "
                             "it was 0.5 s, our choice, not measured); remove the key",
    "recovery.kept_move_angle": "replaced by status.max_template_std (the template's largest displacement covers the "
                                "rotation: 1 deg moves points 50 mm out 0.9 mm); remove the key",
}


def _suggest(word: str, options) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _suggest_key(key: str) -> str:
    """'did you mean' for a dotted key: the same name in another section, else the closest key."""
    name = key.split(".", 1)[1]
    same_name = [k for k in KEYS if k.split(".", 1)[1] == name]
    if same_name:
        return f" (did you mean {same_name[0]!r}?)"
    by_name = difflib.get_close_matches(name, [k.split(".", 1)[1] for k in KEYS], n=1, cutoff=0.6)
    if by_name:
        section = key.split(".", 1)[0]
        matches = [k for k in KEYS if k.split(".", 1)[1] == by_name[0]]
        best = next((k for k in matches if k.startswith(section + ".")), matches[0])
        return f" (did you mean {best!r}?)"
    return _suggest(key, KEYS)
