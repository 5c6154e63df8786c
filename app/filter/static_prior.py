"""A static-bone prior for the refinement's track: hold the base-frame pose where the image is silent.

Import as ``from app.filter.static_prior import StaticPrior``. DESIGN.md "Local refinement and the
estimate's uncertainty"; BENCHMARKS.md §6c (the measurement behind it).

Why. Under a hand covering 80 % of the crest the depth of the visible ridge does not hold the pose:
refined again and again on ONE frame from the true pose, crest_left_03 (static_occluded, seed 0)
slides 0.8 / 3.7 / 3.2 / 61 / 56 mm (frames 150 / 200 / 300 / 400 / 500, hand at 27-80 %), and a
slid pose confirms about as many pixels as the truth (the count of pixels within 3 σ: frame 200
946 vs 873, frame 400 after one refinement 237 vs 209). Leaving out the occluders' edge pixels, or
adding the measurements around the silhouette as ICP does, slid as far (§6c). So no per-frame cost
built from these pixels can stop the slide; the bone's being static can.

Model. The bone is static in the robot's base frame unless the image says otherwise. The prior is a
pose ``T_base_bone`` (the anchor) with an information matrix Λ (6x6, the refinement's coordinates:
δ = (ω, v) in the bone frame about ``Refiner.center``, applied as ``T ← T exp(δ)⁻¹``). Each refined
frame gives a pose T_img (the free refinement, started from the anchor) with information H
(RefineResult.H, inflated by ``covariance_inflation`` for correlated pixels). With δ the increment
from the anchor to T_img:

- **clear or weak frame**: a frame is *clear* when the image alone predicts the template's error
  (refine.template_std of H, inflated) at most ``clear_ratio`` (1.5) times the smallest since the
  last release; under a hand it grows with the hidden share (crest_left_03, seed 0: 0.56 mm clear,
  0.77 at 27 % hidden, 0.93 at 43 %, 2.0 at 45 %, 15 at 80 %). A relative test, not the status's
  absolute 1 mm: at 0.65 m every frame predicts 1.1-1.4 mm and must still refine the pose. The
  caller passes σ on one grid (refine_track: σ · stride_grid / stride), else a stride-1 fit (a small
  silhouette) halves the clearest σ and every stride-2 view after it is weak (BENCHMARKS.md §6c);
- **weak frame: the pose is held** (no update): its fit is dominated by the pull along the crest,
  not by noise (above), and fusing it drifts the pose (measured on crest_right_02, static_occluded
  seed 0, fusing every frame with an absolute 1 mm test instead: 0.29 -> 0.74 mm over 4 s under the
  hand, while one-frame-at-a-time Kalman weights made each step small);
- **clear frame, contradiction test**: Δχ² = δᵀ (H / inflation) δ, the drop of the image's own
  robust cost from the anchor to T_img (its quadratic model). It is large only along directions the
  image constrains. Above ``release_chi2`` (25) the image contradicts the prior: the prior is
  released (anchor ← T_img, Λ ← H / inflation): a bone that moves in view is followed at once.
  Tried on 2026-11-24 and not kept: 4 (under the image's own inflated covariance Δχ² is χ²₆ / 6,
  P(> 4) ~ 5e-4; at rest it stayed <= 1.08). It followed a slowly starting bone (ADD 0.14 -> 0.11
  mm over bone_moves) and a hand-eye error (camera-frame ADD 0.38 -> 0.15 mm on or_calibration),
  but after a fast reposition a wrong track then slid with the image's fits, kept a fit >= 0.6 and
  kept moving, so no trigger fired (or_fast_reposition: 2 of 24 runs never found again, median
  0.42 -> 1.36 s; BENCHMARKS.md §6f). What 25 leaves, a held pose the image contradicts, the status
  reports (status.py, ``held``: χ²₆ at ``status.alpha`` / inflation, 3.62). A
  weak frame never releases: with the quadratic test alone, crest_left_03 released at 75 % hidden
  (Δχ² 27 for a fit that had slid 12 mm) and was lost;
- **clear frame, motion test** (a window over the image's own fits, not against the anchor): Δχ²_W =
  dᵀ (H'_old⁻¹ + H'⁻¹)⁻¹ d, d the increment from the image's fit ``motion_frames`` (9) consecutive
  clear frames ago to this frame's fit (fewer after a weak frame, which empties the window). Above
  ``release_chi2`` the bone is moving: the prior is released onto the image's fit, every clear frame
  while the window spans the move. Why (measured with ``release_chi2`` 25): a bone moving at 5 cm/s
  moves ~0.55 mm a frame, each frame's Δχ² against the anchor stays at 5-13, under 25, so the
  frames were *fused*: with Λ of n frames the
  anchor moves δ/(n+1), the refinement starts from the lagging anchor, and once the lag passes the
  narrow refinement's reach it converges short of the bone (crest_left_02 bone_moves seed 2: 2.8-6.6 mm
  behind during the move, held 3.49 mm off after rest). Measured on that trial: Δχ²_W 0.0-0.2 at rest
  and 27-350 during the move (no overlap); the anchor's own Δχ² cannot separate them because the fit
  it compares starts from the anchor. A hand's slide is not motion to this test: weak frames never
  enter the window, and a slide over seconds moves the fits little within 9 frames (0.1 s at 90 Hz);
- **clear frame, otherwise a Kalman update with no process noise** (a static pose, information form):
  δ* = (Λ + H')⁻¹ H' δ, anchor ← anchor ∘ exp(δ*)⁻¹, Λ ← min(Λ + H', cap), H' = H / inflation.
  In the directions the image constrains H' dominates and the pose follows the image; in the
  directions it does not (the crest's long axis and roll under the hand) Λ from the earlier,
  clearer frames holds the pose. Λ is capped (``max_information_frames`` x the largest H' seen
  since the last release) so that the anchor keeps refining on a clear view;
- **clear frame, the view improves** (``forget_ratio``, 2): with σ_b the template error of the view
  Λ was built on (the release's, or the last discount's), a clear frame with σ <= σ_b / forget_ratio
  discounts Λ ← Λ (σ / σ_b)² and sets σ_b ← σ before it is fused. Why: a view's fits carry a bias of
  the order of the view's own σ that more frames of the same view do not average out, and Λ counted
  them as if they did. Measured after a fast reposition (or_fast_reposition crest_right_03 seed 0,
  scripts/prior_probe.py): 2 s with a quarter of the crest in view (σ 3.5-5 mm) built Λ on a pose
  2.0 mm off; as the camera's view improved (σ 3.0 -> 0.7 mm over 1.5 s) the image's fits lay
  0.7-0.9 mm off, but Λ (140-660 frames' worth of the new view) moved the anchor 1.9 -> 0.6 mm only
  over those 1.5 s. A view that only fluctuates (σ within the clear test's 1.5x) never discounts:
  the static scenes average every clear frame as before (BENCHMARKS.md §6h).

The caller passes H on one grid (refine_track.RefinedTrack._on_grid: a stride-1 fit's H x 1/4), as it passes σ:
a stride-1 fit's errors are not four times smaller than the same view's at stride 2 (the
calibration of BENCHMARKS.md §6: 12.7 against 2.9 for 90 % coverage).

Motion test measured (BENCHMARKS.md §6c, end): bone_moves 8 crests x 3 seeds, after rest + 0.3 s max ADD
0.43 mm (was 3.49 on crest_left_02 seed 2), ADD p95 <= 0.67 mm (was up to 5.5). Since the grid
information (§6h) 0.53 mm (crest_right_03 seed 1): a stride-1 frame's Δχ² is a quarter of what it was,
so the motion test stops releasing a few frames sooner as the bone comes to rest.

Measured (BENCHMARKS.md §6c, commit f82eac8, the lead's 7 s static_occluded trials, 8 CT crests):
seed 0 lost 0-62 % -> 0 % on every crest, ADD median per run 0.14-0.38 mm, 0 frames ok while > 5 mm
off; bone_moves back within 0.13-0.90 mm 0.3 s after rest (the prior is released by the moving
bone's clear frames), the pose lagging a moving bone by up to ~1 mm (p95) meanwhile.

The status never counts Λ: the predicted template error is the image's (H alone), so a frame held
by the prior rather than the image is not ok unless the image itself supports it (status.py's
``max_template_std``); chosen because the prior is only as good as the assumption that the bone
did not move while the image could not see it.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from app.geometry import se3


@dataclass
class StaticPriorConfig:
    """``refine.static_prior`` / ``refine.prior_*``: enabled; release_chi2 (Δχ² of the image's cost
    above which the prior is released); clear_ratio (a frame is *clear* when its predicted template
    error is at most this times the smallest since the last release); max_information_frames (Λ's
    cap in units of the largest frame information); motion_frames (the motion test's window in clear
    frames: the image's fit is compared with its own fit this many clear frames ago; 0 disables);
    forget_ratio (a clear frame whose template error is this many times smaller than the view that
    built Λ discounts Λ by the square of the ratio; 0 disables)."""

    enabled: bool = True
    release_chi2: float = 25.0
    clear_ratio: float = 1.5
    max_information_frames: float = 300.0
    motion_frames: int = 9
    forget_ratio: float = 2.0


def increment(delta: np.ndarray, center: np.ndarray) -> np.ndarray:
    """exp(δ) about ``center`` as a 4x4 (the refinement's update, app/filter/refine.py step 6)."""
    M = se3.from_rotvec_trans(np.asarray(delta[:3], float), np.asarray(delta[3:], float))
    M[:3, 3] += center - M[:3, :3] @ center
    return M


def log_increment(T_from: np.ndarray, T_to: np.ndarray, center: np.ndarray) -> np.ndarray:
    """δ with T_to = T_from exp(δ)⁻¹ (exp about ``center``): inverse of :func:`increment`."""
    from scipy.spatial.transform import Rotation

    M = se3.inverse(T_to) @ T_from
    omega = Rotation.from_matrix(M[:3, :3]).as_rotvec()
    v = M[:3, 3] - center + M[:3, :3] @ center
    return np.concatenate([omega, v])


class StaticPrior:
    """The anchor pose and its information (module docstring)."""

    def __init__(self, config: StaticPriorConfig, center: np.ndarray, inflation: float):
        self.config = config
        self.center = np.asarray(center, float)
        self.inflation = max(float(inflation), 1e-9)
        self.reset()

    def reset(self) -> None:
        self.T_base_bone: np.ndarray | None = None
        self.information = np.zeros((6, 6))
        self._cap = 0.0
        self._best_std = float("inf")
        self._basis_std = float("inf")
        self.discounted = False
        self.released = False
        self.held = False
        self.chi2 = float("nan")
        self.motion_chi2 = float("nan")
        self._fits: deque = deque(maxlen=max(int(self.config.motion_frames), 0) + 1)

    @property
    def active(self) -> bool:
        return self.T_base_bone is not None

    def start(self, T_base_bone: np.ndarray, H: np.ndarray, image_std: float = float("inf")) -> np.ndarray:
        """(Re)start at a pose with the frame's information H and template error (a release, a reseed)."""
        self.T_base_bone = np.array(T_base_bone, float)
        self._best_std = float(image_std)
        self._basis_std = float(image_std)
        H1 = np.asarray(H, float) / self.inflation
        self.information = H1
        self._cap = float(np.trace(H1))
        return self.T_base_bone

    def would_release(self, T_base_bone_image: np.ndarray, H: np.ndarray, image_std: float) -> bool:
        """Whether :meth:`update` with this fit would release the prior (no state change)."""
        if not self.active:
            return True
        if not self._clear(image_std):
            return False
        H1 = np.asarray(H, float) / self.inflation
        delta = log_increment(self.T_base_bone, T_base_bone_image, self.center)
        return self._releases(float(delta @ H1 @ delta), self._motion_chi2(T_base_bone_image, H1))

    def _releases(self, chi2: float, motion_chi2: float) -> bool:
        """A clear frame releases the prior: the contradiction test or the motion test (module docstring)."""
        return chi2 > self.config.release_chi2 or motion_chi2 > self.config.release_chi2

    def _motion_chi2(self, T_base_bone_image: np.ndarray, H1: np.ndarray) -> float:
        """The motion test (module docstring): Δχ²_W = dᵀ (H'_old⁻¹ + H'⁻¹)⁻¹ d between this frame's fit
        and the oldest fit of the window (``motion_frames`` consecutive clear frames ago, fewer just after a
        weak frame or a reset; both the image's alone); (A⁻¹ + B⁻¹)⁻¹ = A (A + B)⁻¹ B, defined where either
        constrains a direction. NaN with no earlier clear fit."""
        if self.config.motion_frames <= 0 or not self._fits:
            return float("nan")
        T_old, H_old = self._fits[0]
        d = log_increment(T_old, T_base_bone_image, self.center)
        combined = H_old @ np.linalg.solve(H_old + H1 + 1e-12 * np.eye(6), H1)
        return float(d @ combined @ d)

    def _clear(self, image_std: float) -> bool:
        """A frame whose image constrains the template about as well as the clearest one since the
        last release (not under a hand): it may release or move the prior."""
        return image_std <= self.config.clear_ratio * self._best_std

    def _discount(self, image_std: float) -> None:
        """Discount Λ when the view has improved (module docstring, "clear frame, the view improves"):
        with σ_b the template error of the view that built Λ, a clear frame with σ <= σ_b / forget_ratio
        scales Λ by (σ / σ_b)² and makes σ the new σ_b."""
        ratio = self.config.forget_ratio
        self.discounted = bool(ratio > 0.0 and np.isfinite(self._basis_std) and image_std * ratio <= self._basis_std)
        if self.discounted:
            self.information = self.information * (image_std / self._basis_std) ** 2
            self._basis_std = image_std

    def update(self, T_base_bone_image: np.ndarray, H: np.ndarray, image_std: float = 0.0) -> np.ndarray:
        """Fuse one frame's refined pose and information; returns the new anchor (module docstring).
        ``image_std`` (m): the predicted template error from the image alone (refine.template_std of
        H); only a clear frame (module docstring) may release or move the prior."""
        self.discounted = False
        if not self.active:
            self.released, self.held, self.chi2 = True, False, float("nan")
            return self.start(T_base_bone_image, H, image_std)
        H1 = np.asarray(H, float) / self.inflation
        delta = log_increment(self.T_base_bone, T_base_bone_image, self.center)
        self.chi2 = float(delta @ H1 @ delta)
        clear = self._clear(image_std)
        self.motion_chi2 = self._motion_chi2(T_base_bone_image, H1) if clear else float("nan")
        if clear:
            self._fits.append((np.array(T_base_bone_image, float), H1))
        else:
            self._fits.clear()   # the window spans consecutive clear frames only
        self.released = clear and self._releases(self.chi2, self.motion_chi2)
        if self.released:
            self.held = False
            return self.start(T_base_bone_image, H, image_std)
        self.held = not clear
        if self.held:
            return self.T_base_bone
        self._best_std = min(self._best_std, float(image_std))
        self._discount(float(image_std))
        total = self.information + H1
        step = np.linalg.solve(total + 1e-12 * np.eye(6), H1 @ delta)
        self.T_base_bone = self.T_base_bone @ se3.inverse(increment(step, self.center))
        self._cap = max(self._cap, float(np.trace(H1)))
        limit = self.config.max_information_frames * self._cap
        trace = float(np.trace(total))
        self.information = total * (limit / trace) if trace > limit else total
        return self.T_base_bone
