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
   the first φ
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
   result turned by each is searched locally and kept when likelier.

**Known failure, measured (BENCHMARKS.md §5):** on a CT crest buried in simulated soft tissue,
the one-frame likelihood is higher at a wrong pose (45 mm / 70 deg off; the bone laid along the
tissue surface, we suppose: ~515 nats) than at the true one (~386), so no sampler finds the
truth from this frame alone, and the status rules do not flag the wrong pose. A tracker started this way
therefore never reports ok (:class:`app.pipeline.tracker.DepthTracker`): the initialiser is for
evaluation, not for the operating room, until the likelihood separates the two.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from app.filter import resampling as rs
from app.filter import weights as lw_ops
from app.filter.estimate import PoseEstimate, estimate
from app.filter.motion import ParticleState
from app.geometry import quaternion as quat
from app.geometry import se3

log = logging.getLogger(__name__)


@dataclass
class SMCInitConfig:
    """Settings of the one-point initialiser.

    particles : N of the sampler ((B): ~100); sigma_t : m, how far the pointed point may lie off the
    surface (pointing error); sigma_r : rad, local orientation move; p_global : share of uniform
    orientation moves; mh_moves : MH sweeps per tempering step; target_ess : ESS / N kept by each
    tempering step; max_steps : tempering steps before φ jumps to 1; max_evaluations : pose
    likelihood evaluations shared by the restarts (each run gets an equal share of what is left;
    past it φ jumps to 1): the budget, counted in work, so a run does the same on a loaded machine
    and a free one; budget_s : s, only a safety net against a stuck backend (a run past it jumps
    to φ = 1 and says so in the log); a correct run stays far below it; surface_samples : points on the mesh for
    the prior's distance; prior_draws : poses drawn from the prior and scored before the first
    tempering step, of which ``particles`` go on (a wider first look at SO(3): with 100-200 draws
    the cloud often settles in a wrong basin); sigma_n : rad, the normal prior (below; 0 = off,
    orientation uniform as in (B)); normal_radius : m, the measured points around the pointed
    point that give its normal; restarts : independent runs, the most likely one kept; symmetry_check : then search the
    mesh's half-turn symmetries of the result (:meth:`OnePointInitialiser._symmetry_check`) from a
    cloud of symmetry_sigma_p (m) / symmetry_sigma_r (rad) around each.
    """

    particles: int = 200
    sigma_t: float = 0.005
    sigma_r: float = 0.15
    p_global: float = 0.2
    mh_moves: int = 4
    target_ess: float = 0.5
    max_steps: int = 40
    max_evaluations: int = 150_000
    budget_s: float = 600.0
    surface_samples: int = 4000
    prior_draws: int = 10000
    sigma_n: float = 0.35
    normal_radius: float = 0.01
    restarts: int = 3
    symmetry_check: bool = True
    symmetry_sigma_p: float = 0.005
    symmetry_sigma_r: float = 0.07


def smc_config_for(tracker_config, **overrides) -> SMCInitConfig:
    """The initialiser's settings from a TrackerConfig's ``init.*`` keys (point_sigma, restarts,
    budget_s), its particles capped at the filter's (the backend's capacity)."""
    values = dict(particles=min(SMCInitConfig.particles, tracker_config.particles),
                  sigma_t=tracker_config.init_point_sigma, restarts=tracker_config.init_restarts,
                  budget_s=tracker_config.init_budget_s)
    values.update({k: v for k, v in overrides.items() if v is not None})
    return SMCInitConfig(**values)


@dataclass
class SMCResult:
    """The sampler's outcome.

    p, q : (N, 3), (N, 4) the final cloud (equally weighted); log_likelihood : (N,) its p(z | x);
    estimate : weighted-mean pose and spread; phis : the tempering schedule reached; acceptance :
    mean MH acceptance per step; seconds : wall time; reached_target : φ got to 1 within the
    step and evaluation budgets by tempering (not by the final jump); symmetry_turned : the symmetry
    check replaced the sampler's cloud; evaluations : pose likelihood evaluations of the whole
    initialisation.
    """

    p: np.ndarray
    q: np.ndarray
    log_likelihood: np.ndarray
    estimate: PoseEstimate
    phis: list[float] = field(default_factory=list)
    acceptance: list[float] = field(default_factory=list)
    seconds: float = 0.0
    reached_target: bool = True
    symmetry_turned: bool = False
    evaluations: int = 0


class SurfacePrior:
    """log p(x) of the module docstring: the pointed point on the mesh surface, orientation uniform."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, point_base: np.ndarray, sigma_t: float,
                 n_samples: int, rng: np.random.Generator):
        import trimesh

        mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
        self.surface_bone, face_index = trimesh.sample.sample_surface(mesh, int(n_samples),
                                                                      seed=int(rng.integers(2**31)))
        self.normals_bone = np.asarray(mesh.face_normals)[face_index]
        self.tree = cKDTree(self.surface_bone)
        self.point_base = np.asarray(point_base, dtype=float).reshape(3)
        self.sigma_t = float(sigma_t)
        self.normal_base: np.ndarray | None = None
        self.sigma_n = 0.0

    def set_normal(self, normal_base: np.ndarray | None, sigma_n: float) -> None:
        """Turn on the normal prior with the measured unit normal (base frame), or off (None)."""
        self.normal_base = None if normal_base is None or sigma_n <= 0 else np.asarray(normal_base, float)
        self.sigma_n = float(sigma_n)

    def nearest(self, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """d(x): distance (m) of the pointed point, in each particle's bone frame, to the surface; and
        the index of the nearest surface sample s*(x)."""
        point_bone = quat.rotate(quat.conjugate(q), self.point_base[None] - p)
        return self.tree.query(point_bone)

    def log_density(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        d, idx = self.nearest(p, q)
        lp = -0.5 * (d / self.sigma_t) ** 2
        if self.normal_base is not None:
            n_base = quat.rotate(q, self.normals_bone[idx])
            angle = np.arccos(np.clip(n_base @ self.normal_base, -1.0, 1.0))
            lp = lp - 0.5 * (angle / self.sigma_n) ** 2
        return lp

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Draws from the prior (approximately: the nearest surface point is taken to be the drawn one)."""
        k = rng.integers(len(self.surface_bone), size=n)
        if self.normal_base is None:
            q = quat.random_uniform(rng, n)
        else:  # R n(s) = n_z up to N(0, σ_n), then a uniform twist about n_z
            align = quat.normalize(rotation_between(self.normals_bone[k], self.normal_base))
            twist = quat.exp_map(self.normal_base[None] * rng.uniform(-np.pi, np.pi, (n, 1)))
            tilt = quat.exp_map(_tangent_noise(self.normal_base, self.sigma_n, n, rng))
            q = quat.normalize(quat.multiply(tilt, quat.multiply(twist, align)))
        p = self.point_base[None] - quat.rotate(q, self.surface_bone[k]) + rng.normal(0.0, self.sigma_t, (n, 3))
        return p, q


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) of the shortest rotations taking unit vectors a (N, 3) onto b (3,)."""
    b = np.broadcast_to(b, a.shape)
    w = 1.0 + np.sum(a * b, axis=1)
    xyz = np.cross(a, b)
    opposite = w < 1e-9   # a = -b: any axis orthogonal to a, by 180 degrees
    if opposite.any():
        ortho = np.cross(a[opposite], np.array([1.0, 0.0, 0.0]))
        small = np.linalg.norm(ortho, axis=1) < 1e-6
        ortho[small] = np.cross(a[opposite][small], np.array([0.0, 1.0, 0.0]))
        xyz[opposite], w[opposite] = ortho / np.linalg.norm(ortho, axis=1, keepdims=True), 0.0
    return quat.normalize(np.column_stack([w, xyz]))


def _tangent_noise(normal: np.ndarray, sigma: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Rotation vectors (n, 3) ~ N(0, σ²) about axes orthogonal to ``normal``: tilts of the normal."""
    r = rng.normal(0.0, sigma, (n, 3))
    return r - np.outer(r @ normal, normal)


def measured_normal(depth: np.ndarray, camera, T_base_camera: np.ndarray, point_base: np.ndarray,
                    radius: float, min_points: int = 8) -> np.ndarray | None:
    """The surface normal (base frame, unit, facing the camera) of the measured points within ``radius``
    of ``point_base``: the smallest principal axis of their covariance; None with fewer than
    ``min_points`` such points (the pointed point hidden or unmeasured)."""
    T_camera_base = se3.inverse(np.asarray(T_base_camera, float))
    point_camera = T_camera_base[:3, :3] @ point_base + T_camera_base[:3, 3]
    points, _ = camera.backproject(np.where(np.isfinite(depth), depth, 0.0))
    near = points[np.linalg.norm(points - point_camera, axis=1) < radius]
    if len(near) < min_points:
        return None
    centred = near - near.mean(axis=0)
    normal = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    if normal @ point_camera > 0:   # face the camera (at the origin)
        normal = -normal
    return T_base_camera[:3, :3] @ normal


def mesh_symmetries(vertices: np.ndarray, faces: np.ndarray, max_residual: float = 0.003, n_samples: int = 4000,
                    iterations: int = 50, seed: int = 0) -> list[np.ndarray]:
    """The mesh's approximate half-turn self-symmetries S (4x4, bone frame): S(mesh) ≈ mesh.

    From the half turn about each principal axis through the centroid, a trimmed point-to-point ICP
    (Kabsch on the nearest 80 %) of the surface samples onto themselves; a result is kept when the
    median distance of the moved samples to the surface is below ``max_residual`` (m). A crest is a
    ridge: turned end for end about its normal it nearly covers itself (the synthetic crest: 2.1 mm
    median; CT crest_right_03: 2.4 and 2.9 mm about two axes).
    """
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
    pts, _ = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
    tree = cKDTree(pts)
    centre = pts.mean(axis=0)
    axes = np.linalg.eigh(np.cov((pts - centre).T))[1]
    found = []
    for k in range(3):
        R = quat.to_matrix(quat.exp_map(axes[:, k][None] * np.pi))[0]
        t = centre - R @ centre
        for _ in range(iterations):
            moved = pts @ R.T + t
            d, j = tree.query(moved)
            keep = d <= np.percentile(d, 80)
            dR, dt = _kabsch(moved[keep], pts[j[keep]])
            R, t = dR @ R, dR @ t + dt
        if np.median(tree.query(pts @ R.T + t)[0]) < max_residual:
            found.append(se3.make_pose(R, t))
    return found


def _kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R and translation t minimising |R a + t - b|² (Kabsch / Umeyama without scale)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def next_phi(phi: float, log_lik: np.ndarray, target_ess: float) -> float:
    """The largest φ' in (φ, 1] whose incremental weights (φ' - φ) log p(z | x) keep ESS >= target · N."""
    n = len(log_lik)

    def ess_ratio(step: float) -> float:
        return lw_ops.ess(lw_ops.normalise_log_weights(step * log_lik)) / n

    if ess_ratio(1.0 - phi) >= target_ess:
        return 1.0
    lo, hi = 0.0, 1.0 - phi
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if ess_ratio(mid) >= target_ess:
            lo = mid
        else:
            hi = mid
    return phi + max(lo, 1e-9)


def rotate_about(point: np.ndarray, p: np.ndarray, q: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the rotations dq (N, 4) about ``point`` (3,) to poses (p, q): q' = dq ⊗ q, p' = point + R(dq)(p - point)."""
    return point[None] + quat.rotate(dq, p - point[None]), quat.normalize(quat.multiply(dq, q))


class OnePointInitialiser:
    """The sampler of the module docstring over a likelihood backend (``log_likelihood(T_camera_bone, depth)``).

    Parameters
    ----------
    backend : the particle filter's LikelihoodBackend (its capacity must be >= config.particles)
    camera : the PinholeCamera of the backend's images (the filter's resolution)
    vertices, faces : the tracking mesh (bone frame, m, outward normals)
    config : SMCInitConfig
    rng : np.random.Generator
    """

    def __init__(self, backend, camera, vertices: np.ndarray, faces: np.ndarray, config: SMCInitConfig,
                 rng: np.random.Generator):
        self.backend, self.camera, self.vertices, self.faces = backend, camera, vertices, faces
        self._symmetries: list[np.ndarray] | None = None
        self.config, self.rng = config, rng

    def run(self, depth: np.ndarray, T_base_camera: np.ndarray, point_base: np.ndarray,
            sigma_t: float | None = None) -> SMCResult:
        """Sample π from the depth image (filter resolution), the camera pose and the pointed point.

        ``restarts`` independent runs; the one whose cloud has the highest mean log-likelihood wins
        (a run that settled in a wrong basin, e.g. the crest turned end for end, scores hundreds of
        nats lower). ``max_evaluations`` is shared by the runs (``budget_s``: the wall-time safety net).
        """
        t_start = time.perf_counter()
        prior, log_lik = self._target(depth, T_base_camera, point_base, sigma_t)
        best: SMCResult | None = None
        restarts = max(1, self.config.restarts)
        for k in range(restarts):
            left = self.config.max_evaluations - log_lik.evaluations
            if best is not None and (left <= 0 or time.perf_counter() - t_start > self.config.budget_s):
                break
            limit = log_lik.evaluations + left // (restarts - k)
            result = self._run_once(prior, log_lik, limit, t_start + self.config.budget_s)
            if best is None or np.mean(result.log_likelihood) > np.mean(best.log_likelihood):
                best = result
        if self.config.symmetry_check:
            best = self._symmetry_check(best, prior, log_lik)
        best.seconds = time.perf_counter() - t_start
        best.evaluations = log_lik.evaluations
        return best

    def _target(self, depth, T_base_camera, point_base, sigma_t):
        """The prior (with the measured normal) and the log-likelihood function of one frame."""
        c = self.config
        prior = SurfacePrior(self.vertices, self.faces, point_base, c.sigma_t if sigma_t is None else sigma_t,
                             c.surface_samples, self.rng)
        normal = measured_normal(depth, self.camera, T_base_camera, prior.point_base, c.normal_radius) \
            if c.sigma_n > 0 else None
        if c.sigma_n > 0 and normal is None:
            log.warning("one-point initialisation: too few measured points at the pointed point for its normal: "
                        "orientation prior uniform")
        prior.set_normal(normal, c.sigma_n)
        T_camera_base = se3.inverse(np.asarray(T_base_camera, float))

        def log_lik(p, q):
            log_lik.evaluations += len(p)
            ll = np.asarray(self.backend.log_likelihood(T_camera_base @ se3.from_quat_trans(q, p), depth), float)
            return np.where(np.isfinite(ll), ll, -1e12)

        log_lik.evaluations = 0
        return prior, log_lik

    def _symmetry_check(self, result: SMCResult, prior: SurfacePrior, log_lik) -> SMCResult:
        """Look for the bone turned by one of the mesh's half-turn symmetries, and keep it if likelier.

        A ridge turned end for end covers much of its own visible surface, and the sampler's
        restarts can all settle there (hundreds of nats below the true pose, which the status rules
        then fail to tell apart). For each symmetry S of :func:`mesh_symmetries` (and S⁻¹), a cloud
        of N poses around x S (x: the result's mean pose; spread ``symmetry_sigma_p`` /
        ``symmetry_sigma_r``, because the visible part's symmetry differs from the whole mesh's by
        millimetres and degrees) is tempered to the likelihood by :meth:`_temper` from φ = 0 with
        local moves only. The candidate cloud replaces the result
        when its mean log-likelihood is higher.
        """
        c, rng = self.config, self.rng
        if self._symmetries is None:
            self._symmetries = mesh_symmetries(self.vertices, self.faces)
        x = result.estimate.T_base_bone
        best = result
        for S in self._symmetries:
            for S_k in (S, se3.inverse(S)):
                q0, t0 = se3.to_quat_trans(x @ S_k)
                n = len(result.p)
                p = t0 + rng.normal(0.0, c.symmetry_sigma_p, (n, 3))
                q = quat.normalize(quat.multiply(quat.exp_map(rng.normal(0.0, c.symmetry_sigma_r, (n, 3))),
                                                 np.repeat(q0[None], n, axis=0)))
                ll = log_lik(p, q)
                phi = next_phi(0.0, ll, c.target_ess)
                idx = rs.systematic(phi * ll, rng.random())
                p, q, ll = p[idx], q[idx], ll[idx]
                p, q, ll, lp, _, _, reached = self._temper(p, q, ll, prior.log_density(p, q), phi, prior, log_lik,
                                                           None, None, local=True)
                log.debug("symmetry check: candidate %.0f vs result %.0f (mean log-likelihood)", np.mean(ll),
                          np.mean(best.log_likelihood))
                if reached and np.mean(ll) > np.mean(best.log_likelihood):
                    log.info("one-point initialisation: the bone turned by a symmetry of its mesh explains the "
                             "image better (mean log-likelihood %.0f vs %.0f): taken", np.mean(ll),
                             np.mean(best.log_likelihood))
                    best = SMCResult(p, q, ll, estimate(p, q, lw_ops.uniform_log_weights(n)), result.phis,
                                     result.acceptance, result.seconds, result.reached_target, symmetry_turned=True)
        return best

    def _run_once(self, prior: SurfacePrior, log_lik, limit: int, deadline: float) -> SMCResult:
        """One run of the sampler (module docstring, steps 1-3), tempering until ``log_lik`` has made
        ``limit`` evaluations (or, as a safety net, until ``deadline``, perf_counter s)."""
        c, rng = self.config, self.rng
        t_start = time.perf_counter()
        # step 1 on a wider draw: score prior_draws poses, keep `particles` of them at the first φ
        p, q = prior.sample(max(c.prior_draws, c.particles), rng)
        ll = np.concatenate([log_lik(p[i:i + c.particles], q[i:i + c.particles]) for i in range(0, len(p), c.particles)])
        phi = next_phi(0.0, ll, c.target_ess * c.particles / len(p))
        idx = rs.systematic(phi * ll, rng.random(), c.particles)
        p, q, ll = p[idx], q[idx], ll[idx]
        p, q, ll, _, phis, acceptance, reached = self._temper(p, q, ll, prior.log_density(p, q), phi, prior, log_lik,
                                                              limit, deadline)
        seconds = time.perf_counter() - t_start
        pose = estimate(p, q, lw_ops.uniform_log_weights(len(p)))
        log.info("one-point initialisation: %d tempering steps, %.2f s, spread %.1f mm / %.1f deg%s", len(phis) - 1,
                 seconds, 1e3 * pose.position_spread, np.degrees(pose.rotation_spread),
                 "" if reached else " (budget reached: φ jumped to 1)")
        return SMCResult(p, q, ll, pose, phis, acceptance, seconds, reached)

    def _temper(self, p, q, ll, lp, phi, prior, log_lik, limit: int | None, deadline: float | None,
                local: bool = False):
        """MH sweeps at φ, then (step 2) the next φ, resampling, sweeps, until φ = 1; past ``max_steps``,
        ``limit`` evaluations of ``log_lik`` or (safety net) ``deadline``, φ jumps to 1. Returns the cloud, the φ schedule (from 0), the acceptance per
        step and whether φ = 1 was reached by tempering."""
        c, rng = self.config, self.rng
        phis, acceptance, scale, scale_r, reached = [0.0, phi] if phi > 0 else [0.0], [], 1.0, 1.0, True
        while True:
            p, q, ll, lp, scale, scale_r, accepted = self._sweeps(p, q, ll, lp, phi, c.mh_moves, prior, log_lik,
                                                                  scale, scale_r, local)
            acceptance.append(accepted)
            if phi >= 1.0:
                return p, q, ll, lp, phis, acceptance, reached
            late = deadline is not None and time.perf_counter() > deadline
            if late:
                log.warning("one-point initialisation: the %.0f s safety net was reached (init.budget_s): stopping", c.budget_s)
            out_of_budget = len(phis) > c.max_steps or late or (limit is not None and log_lik.evaluations >= limit)
            new_phi = 1.0 if out_of_budget else next_phi(phi, ll, c.target_ess)
            reached &= not out_of_budget
            idx = rs.resample("systematic", lw_ops.normalise_log_weights((new_phi - phi) * ll), rng)
            p, q, ll, lp = p[idx], q[idx], ll[idx], lp[idx]
            phi = new_phi
            phis.append(phi)

    def _sweeps(self, p, q, ll, lp, phi, n_sweeps, prior, log_lik, scale, scale_r, local=False):
        """``n_sweeps`` MH sweeps at φ, alternating position and orientation moves (module docstring);
        ``local``: no global orientation jumps. Returns the cloud, the tuned scales and the acceptance."""
        rng, accepted = self.rng, 0.0
        for sweep in range(n_sweeps):
            if sweep % 2 == 0:
                p_new, q_new = self._position_move(p, q, scale)
            else:
                p_new, q_new = self._orientation_move(p, q, prior, scale_r, 0.0 if local else self.config.p_global)
            ll_new, lp_new = log_lik(p_new, q_new), prior.log_density(p_new, q_new)
            accept = np.log(rng.uniform(size=len(p))) < (lp_new + phi * ll_new) - (lp + phi * ll)
            p, q = np.where(accept[:, None], p_new, p), np.where(accept[:, None], q_new, q)
            ll, lp = np.where(accept, ll_new, ll), np.where(accept, lp_new, lp)
            rate = float(accept.mean())
            accepted += rate / n_sweeps
            if sweep % 2 == 0:
                scale *= np.exp(rate - 0.3)
            else:
                scale_r = float(np.clip(scale_r * np.exp(rate - 0.3), 0.01, 1.0))
        return p, q, ll, lp, scale, scale_r, accepted

    def _position_move(self, p: np.ndarray, q: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        cov = np.cov(p.T) + np.eye(3) * 1e-8
        step = self.rng.multivariate_normal(np.zeros(3), (scale * 2.38 / np.sqrt(3)) ** 2 * cov, size=len(p))
        return p + step, q

    def _orientation_move(self, p: np.ndarray, q: np.ndarray, prior: SurfacePrior,
                          scale_r: float, p_global: float) -> tuple[np.ndarray, np.ndarray]:
        """A rotation δ about the pointed point: local N(0, (scale_r σ_r)²), scale_r tuned towards ~30 %
        acceptance; with probability ``p_global`` a uniform one (with the normal prior: a uniform
        twist about the measured normal, which keeps the prior's normal term). Both are symmetric
        (δ and δ⁻¹ equally likely)."""
        n, c, rng = len(p), self.config, self.rng
        dq = quat.exp_map(rng.normal(0.0, scale_r * c.sigma_r, (n, 3)))
        jump = rng.uniform(size=n) < p_global
        if prior.normal_base is None:
            dq[jump] = quat.random_uniform(rng, int(jump.sum()))
        else:
            dq[jump] = quat.exp_map(prior.normal_base[None] * rng.uniform(-np.pi, np.pi, (int(jump.sum()), 1)))
        return rotate_about(prior.point_base, p, q, dq)


def seed_state(result: SMCResult, n: int, rng: np.random.Generator) -> ParticleState:
    """The filter's N particles drawn from the sampler's cloud (systematic), at rest, equally weighted."""
    idx = rs.systematic(lw_ops.uniform_log_weights(len(result.p)), rng.random(), n)
    return ParticleState(result.p[idx].copy(), np.zeros((n, 3)), result.q[idx].copy(), np.zeros((n, 3)),
                         lw_ops.uniform_log_weights(n))
