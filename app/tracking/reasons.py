"""The reason codes: why a frame's status is not ok, each with the test it belongs to and its config key.

Import as ``from app.tracking.reasons import REASONS, reason_shares``. Every rule that lowers the
status (app/filter/status.py ``Reason``), every lifecycle cap (app/filter/recovery.py) and every
session condition (app/session/loop.py) names one of these codes; ``status.csv`` writes them
(``stamp,status,state,reasons``), the summaries give the share of frames each blocked, and the
README's table is generated from :data:`REASONS` (tests/test_reasons.py checks that it is current).
"""
from __future__ import annotations

from collections import Counter

# code: (test, what it means, the config key(s) behind it)
REASONS: dict[str, tuple[str, str, str]] = {
    "no_pose": ("session", "no camera pose (robot joints missing at the frame's stamp)", "recovery.after_uncertain_s"),
    "no_frames": ("session", "the camera delivered no frame", "loop.stall_timeout_s"),
    "not_tracking": ("session", "the session has no tracker", "-"),
    "not_weighed": ("seen", "the frame was not weighed (no pose, no valid depth, or the bone hidden)", "-"),
    "unseen": ("seen", "too few of the bone's pixels are visible", "status.min_covered_pixels"),
    "not_refined": ("seen", "the refinement did not converge on this frame, or is off (then never ok)",
                    "refine.enabled"),
    "unconfirmed": ("seen", "the refined fit confirms too little of the bone's expected visible surface",
                    "status.min_fitness"),
    "imprecise": ("seen", "the template's predicted error from the fit's information exceeds the tolerance",
                  "status.max_template_std, status.covariance_inflation"),
    "behind": ("consistent", "more measurements lie behind the refined model than this image's noise explains "
               "(at level status.alpha, noise scale and correlation measured on the fitted surface)",
               "status.max_behind_excess, status.alpha"),
    "misfit": ("consistent", "almost no pixel fits the estimate (lost)", "status.lost_inlier_fraction"),
    "ambiguous": ("unique", "another pose that moves the template beyond the tolerance explains the image as well",
                  "refine.nearby_margin"),
    "moving": ("steady", "the bone is moving or settling", "status.uncertain_speed, status.settle_s"),
    "held": ("steady", "the image's own fit contradicts the pose held by the static prior",
             "status.alpha, status.covariance_inflation"),
    "spread": ("filter", "the particles are spread too wide (lost)",
               "refine.competitor_distance"),
    "nan": ("filter", "NaN log-likelihoods", "-"),
    "initialising": ("lifecycle", "no pose yet: waiting for a frame to start from", "init.method"),
    "point_start": ("lifecycle", "started from a point without the detector's confirmation", "init.method"),
    "confirming": ("lifecycle", "a re-initialised pose away from the last ok one awaits its evidence",
                   "recovery.confirm_frames"),
    "searching": ("lifecycle", "a trigger found the track suspect: a re-initialisation is due, or a search found "
                  "nothing and is retried (the text names the trigger: the triggers' table)", "recovery.*"),
    "other": ("-", "a reason without a code (a plugin's)", "-"),
}


def reason_shares(reasons: list[tuple[str, ...]], states: list[str]) -> dict:
    """For a summary: ``blocked_by`` {code: share of the frames it was among the reasons} and
    ``state_fraction`` {state: share of the frames} (sorted, largest first)."""
    n = len(reasons)
    blocked = Counter(code for codes in reasons for code in set(codes))
    state_counts = Counter(s for s in states if s)
    return {"blocked_by": {c: k / n for c, k in blocked.most_common()} if n else {},
            "state_fraction": {s: k / n for s, k in state_counts.most_common()} if n else {}}


def markdown_table() -> str:
    """The README's table of reason codes."""
    rows = ["| code | test | meaning | config |", "|---|---|---|---|"]
    rows += [f"| `{c}` | {t} | {m} | `{k}` |" if k != "-" else f"| `{c}` | {t} | {m} | - |"
             for c, (t, m, k) in REASONS.items()]
    return "\n".join(rows)
