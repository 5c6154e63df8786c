"""Pose from one depth frame and one pointed 3D point: the static SMC sampler of publication (B).

DESIGN.md "Initialisation from one point" ((B) chapters 4-6). The target is the posterior of the
bone pose x = (t, q) given one depth image z and a point ``point_base`` that a surgeon pointed at
on the bone's surface (base frame)::

    π(x) ∝ p(x) · p(z | x)
    p(x) = N(d(x); 0, σ_t²) · U(SO(3))    d(x) = distance from R(q)ᵀ (point_base - t) to the mesh surface

i.e. the pointed point lies on the bone's surface up to σ_t, the orientation is uniform. (B)
writes the position prior as N(point, σ_t) on the object's position; with a surface point and a
centred mesh the distance form says the same without knowing which surface point was pointed at.
Our addition, the **normal prior** (``sigma_n`` > 0): the depth image gives the surface normal n_z
at the pointed point (a plane fitted to the measured points within ``normal_radius``, facing the
camera), and the bone's outward normal there should match it::

    p(x) = N(d(x); 0, σ_t²) · N(∠(R(q) n(s*(x)), n_z); 0, σ_n²)

with s*(x) the surface point nearest the pointed point. This leaves one rotation (about n_z) and
the surface point (2 DOF) to search instead of all of SO(3) x surface (BENCHMARKS.md §5 lists
what each part changed). Without
enough measured points at the pointed point (hidden, invalid) the prior falls back to (B)'s.

The sampler moves a cloud of ``particles`` (200; (B): ~100) from the prior to π through the tempered targets
π_φ ∝ p(x) p(z | x)^φ, 0 = φ_0 < φ_1 < ... < φ_K = 1 ((B) ch. 5; DESIGN.md: φ_t = t/T):

1. draw ``prior_draws`` (10,000) poses from the prior: q uniform (normalised 4D Gaussian; with
   the normal prior: R n(s) = n_z up to σ_n, a uniform twist about n_z), a surface point s uniform
   on the mesh, t = point - R(q) s + N(0, σ_t² I); score them and keep ``particles`` of them at
   the first φ. The draws are scored at a coarse level (``coarse_levels``: 40x30 and the mesh
   decimated to 250 triangles for the 160x120 filter), the tempering runs at the next (80x60, 500
   triangles), and the end at the filter's: a sequence of SMC targets may change likelihoods,
   each change reweighted (:mod:`.levels`, :meth:`.Tempering.switch`)
2. repeat until φ = 1: the next φ is the largest with ESS(w) >= ``target_ess`` · N for the
   incremental weights w_j ∝ p(z | x_j)^(φ' - φ) (adaptive tempering, Jasra et al. 2011: the fixed
   schedule t/T with T steps is the special case that collapses on this likelihood, whose log
   differences between poses are hundreds of nats); resample (systematic); then ``mh_moves``
   Metropolis-Hastings sweeps at φ', each either
   - a position move t' = t + ε, ε ~ N(0, c² Σ) with Σ the cloud's position covariance (adaptive,
     c tuned towards ~30 % acceptance), or
   - an orientation move about the pointed point: a local rotation δ = exp(N(0, σ_r² I)), or with
     probability ``p_global`` a uniform δ (with the normal prior: a uniform twist about n_z);
     q' = δ ⊗ q, t' = point + R(δ)(t - point), so the surface point under the pointed point stays
     there
   all symmetric, so the acceptance is min(1, π_φ(x') / π_φ(x)).
3. the result is the equally weighted cloud at φ = 1 and its weighted-mean pose; the particle
   filter is seeded from it (:func:`seed_state`).
4. ``restarts`` independent runs, the likeliest kept; then the **symmetry check**: a crest is a
   ridge, and turned end for end (a half turn about its normal) it covers most of its own
   visible surface, a basin the restarts could all settle in (measured: half of the runs on the
   synthetic crest, 73 mm / 179 deg off, and the filter then reported ok). The mesh's half-turn
   self-symmetries are found once by ICP of the mesh onto itself (:func:`mesh_symmetries`); the
   result turned by each is searched locally and kept when likelier. Then the winner moves to the
   filter's resolution and is tempered to its φ = 1 (the last level).

**Known failure, measured (BENCHMARKS.md §5):** on a CT crest buried in simulated soft tissue,
the one-frame likelihood is higher at a wrong pose (45 mm / 70 deg off; the bone laid along the
tissue surface, we suppose: ~515 nats) than at the true one (~386), so no sampler finds the
truth from this frame alone, and the status rules do not flag the wrong pose. A tracker started this way
therefore never reports ok (:class:`app.pipeline.tracker.DepthTracker`): the initialiser is for
evaluation, not for the operating room, until the likelihood separates the two.

Modules: :mod:`.geometry` (rotations, the measured normal, the mesh's symmetries), :mod:`.prior`
(:class:`SurfacePrior`), :mod:`.levels` (the likelihoods at each resolution, the evaluation budget,
the non-finite policy: NaN / +inf -> -inf, counted), :mod:`.tempering` (ESS rule, MH moves, the
level switch), :mod:`.initialiser` (:class:`OnePointInitialiser`, restarts, symmetry check).
"""
from app.filter.smc_init.geometry import (kabsch, measured_normal, mesh_symmetries, rotate_about,
                                          rotation_between, tangent_noise)
from app.filter.smc_init.initialiser import OnePointInitialiser, SMCInitConfig, SMCResult, seed_state, smc_config_for
from app.filter.smc_init.levels import Budget, Level, evaluate, make_levels, tempered
from app.filter.smc_init.prior import SurfacePrior
from app.filter.smc_init.tempering import Cloud, StepScales, Tempered, Tempering, next_phi

__all__ = ["Budget", "Cloud", "Level", "OnePointInitialiser", "SMCInitConfig", "SMCResult", "StepScales",
           "SurfacePrior", "Tempered", "Tempering", "evaluate", "kabsch", "make_levels", "measured_normal",
           "mesh_symmetries", "next_phi", "rotate_about", "rotation_between", "seed_state", "smc_config_for",
           "tangent_noise", "tempered"]
