"""Named simulation scenarios: what moves, what occludes, what fails, and for how long.

Each scenario is a :class:`Scenario` (plain parameters, no behaviour) registered by name in
``SCENARIOS``; :func:`get_scenario` raises a ``ValueError`` listing the valid names. The
standard four (issue 2) are ``static_clear``, ``static_occluded`` (hand occlusion rising to 80 %
and back), ``bone_moves`` (up to 5 cm/s and 30 deg/s, then rest) and ``dropouts`` (300 ms gaps).
The ``or_*`` scenarios reproduce DESIGN.md's "What the operating room does to the tracker";
``static_far`` (0.65 m instead of 0.42 m) and ``static_other_side`` (the bone turned 180 deg about its
crest-up axis) complete issue 12's static scenes.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace


@dataclass(frozen=True)
class Scenario:
    """Parameters of one simulated trial (metres, seconds, radians, degrees where named _deg).

    occlusion_profile : list of (time s, fraction) knots of the hand's target occlusion of the
        bone's visible pixels, linearly interpolated; empty = no hand.
    bone_motion : list of (start s, duration s, translation (3,) m in the base frame,
        rotation vector (3,) rad) minimum-jerk moves of the bone.
    gaps : list of (start s, duration s) intervals with no frames (camera dropouts).
    """

    name: str
    description: str
    seconds: float = 8.0
    occlusion_profile: tuple[tuple[float, float], ...] = ()
    instrument: bool = True
    bone_motion: tuple[tuple[float, float, tuple[float, float, float], tuple[float, float, float]], ...] = ()
    gaps: tuple[tuple[float, float], ...] = ()
    drop_probability: float = 0.01          # random single dropped frames
    invalid_probability: float = 0.01       # random invalid pixels
    init_error_mm: float = 5.0              # initial pose error (translation)
    init_error_deg: float = 3.0             # initial pose error (rotation)
    hand_eye_error_mm: float = 0.0          # trial.yaml's hand-eye vs the true one
    hand_eye_error_deg: float = 0.0
    clock_offset_s: float = 0.0             # robot clock minus camera clock
    encoder_noise_rad: float = 1e-5
    depth_scale_error: float = 0.0          # relative (0.005 = 0.5 %)
    depth_bias_m: float = 0.0               # amplitude of a smooth bias across the image
    specular_fraction: float = 0.0          # invalid blobs on the bone (wet, specular)
    tissue_patch_m: float = 0.0             # residual soft tissue thickness on part of the crest
    graft_cut_at_s: float | None = None     # time a 20x10x10 mm graft is cut out of the crest
    full_occlusion: tuple[float, float] | None = None   # (start, duration): a hand over everything
    camera_distance_m: float = 0.42         # bone origin in front of the camera's start pose (world.CAMERA_TO_BONE_M)
    bone_yaw_deg: float = 0.0               # bone turned about its crest-up axis: 180 = seen from the other side
    extra: dict = field(default_factory=dict)


_MOVE = ((1.5, 2.0, (0.05, 0.0, 0.0), (0.0, 0.0, 0.5236)),)  # 5 cm and 30 deg in 2 s (peak ~4.7 cm/s, 28 deg/s)

SCENARIOS: dict[str, Scenario] = {}


def _register(s: Scenario) -> None:
    SCENARIOS[s.name] = s


_register(Scenario("static_clear", "static bone, moving camera, no occluders", seconds=6.0, instrument=False))
_register(Scenario(
    "static_occluded", "static bone; a hand covers up to 80 % of the bone's pixels and withdraws; an instrument passes",
    seconds=10.0, occlusion_profile=((0.0, 0.0), (1.0, 0.0), (4.0, 0.8), (6.0, 0.8), (9.0, 0.0), (10.0, 0.0)),
))
_register(Scenario("bone_moves", "the surgeon repositions the bone (5 cm, 30 deg at <= 5 cm/s, 30 deg/s), then rest",
                   seconds=7.0, bone_motion=_MOVE))
_register(Scenario("dropouts", "static bone; the camera drops out for 300 ms three times", seconds=8.0,
                   gaps=((2.0, 0.3), (4.0, 0.3), (6.0, 0.3))))
_register(Scenario("or_calibration", "hand-eye off by 2 mm and 0.3 deg, robot clock 4 ms off, encoder noise",
                   seconds=6.0, hand_eye_error_mm=2.0, hand_eye_error_deg=0.3, clock_offset_s=0.004, encoder_noise_rad=5e-5))
_register(Scenario("or_model_mismatch", "residual soft tissue on the crest, then a 20x10x10 mm graft is cut out",
                   seconds=8.0, tissue_patch_m=0.003, graft_cut_at_s=3.0))
_register(Scenario("or_depth_bias", "0.5 % depth scale error, 1 mm smooth bias, wet specular bone (invalid blobs)",
                   seconds=6.0, depth_scale_error=0.005, depth_bias_m=0.001, specular_fraction=0.15))
_register(Scenario("or_full_occlusion", "a hand covers the whole bone for 1 s while the camera keeps moving",
                   seconds=7.0, full_occlusion=(2.5, 1.0)))
_register(Scenario("or_fast_reposition", "the pelvis is moved 12 cm at up to 25 cm/s and 90 deg/s",
                   seconds=5.0, bone_motion=((1.5, 0.9, (0.12, 0.0, 0.0), (0.0, 0.0, 0.785)),)))
_register(Scenario("or_coarse_start", "initial alignment off by 15 mm and 12 deg", seconds=6.0,
                   init_error_mm=15.0, init_error_deg=12.0, instrument=False))
_register(Scenario("or_deep_tissue", "static; the crest stands only ~10 mm out of the soft tissue (world.TISSUE_PROTRUSION_M) "
                   "and 3 mm of residual tissue lies on a third of the ridge (issue 12)",
                   seconds=6.0, tissue_patch_m=0.003, instrument=False))

_register(Scenario("static_far", "static bone seen from 0.65 m (the crest covers ~2k of the 307k pixels), no occluders",
                   seconds=6.0, instrument=False, camera_distance_m=0.65))
_register(Scenario("static_other_side", "static bone seen from the other side of the table (turned 180 deg about its "
                   "crest-up axis), no occluders", seconds=6.0, instrument=False, bone_yaw_deg=180.0))

STANDARD = ("static_clear", "static_occluded", "bone_moves", "dropouts")
DEFAULT_SCENARIO = "static_occluded"


def get_scenario(name: str, seconds: float | None = None) -> Scenario:
    """The registered scenario ``name`` (optionally with another duration)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario '{name}'; valid: {', '.join(SCENARIOS)}")
    scenario = SCENARIOS[name]
    return replace(scenario, seconds=float(seconds)) if seconds else scenario
