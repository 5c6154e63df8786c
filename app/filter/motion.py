"""Particle state and the motion model: decaying velocity driven by white-noise accelerations.

Import as ``from app.filter import motion``. One particle is a hypothesis of the bone's pose
``T_base_bone`` (the bone in the robot base frame: camera motion is not bone motion) and its rates:

- p (N, 3) position of the bone frame's origin in the base frame, m
- v (N, 3) linear velocity in the base frame, m/s
- q (N, 4) unit quaternions (w, x, y, z), the bone's orientation in the base frame (R_base_bone)
- omega (N, 3) angular rate in the BASE frame, rad/s
- lw (N,) log-weights (see :mod:`app.filter.weights`)

Transition (DESIGN.md "Transition", (A) eq. 8-10), ΔT the time since the last processed frame:

    p_t = p_{t-1} + ΔT v_{t-1} + ΔT²/2 w_p          w_p ~ N(0, σ_a² I)
    v_t = λ_v v_{t-1} + ΔT w_p                      (the same w_p draw)
    ω_t = λ_v ω_{t-1} + ΔT w_ω                      w_ω ~ N(0, σ_α² I)
    q_t = exp(ΔT ω_t) ⊗ q_{t-1}

``exp`` is the rotation-vector exponential (cos(ΔT|ω|/2), ω/|ω| sin(ΔT|ω|/2)), i.e. DESIGN's
exp(ΔT/2 · ω) of a pure quaternion, computed exactly (not (A) eq. 10's second-order increment).
Frame choice: ω is the angular rate in the base frame, so the increment multiplies on the LEFT
(q_t = Δq ⊗ q_{t-1}); DESIGN's q ⊗ exp(.) would be a body-frame rate. The rotation turns the bone
about its own origin p (position and orientation are propagated independently). The estimate
(:mod:`app.filter.estimate`) and the initialisers perturb orientations the same way (left).

Closed form of one position step for a known ΔT (per axis, from v_{t-1}): Var(p) = ΔT⁴/4 σ_a²,
Var(v) = ΔT² σ_a², Cov(p, v) = ΔT³/2 σ_a²; for the rotation increment from ω_{t-1}: the rotation
vector ΔT ω_t has mean ΔT λ_v ω_{t-1} and covariance ΔT⁴ σ_α² I. A dropped frame doubles ΔT.

Defaults: σ_a = 5 m/s², σ_α = 50 rad/s² ((A)), λ_v = 0.9 ((B); (A) used 0.95).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from app.filter.weights import uniform_log_weights
from app.geometry import quaternion as quat
from app.geometry import se3


@dataclass
class MotionParams:
    """Parameters of the transition (module docstring).

    sigma_a : m/s², std of the white-noise linear acceleration w_p ((A): 5)
    sigma_alpha : rad/s², std of the white-noise angular acceleration w_ω ((A): 50)
    lambda_v : velocity decay per step in [0, 1] ((B): 0.9; (A): 0.95; 0 for quasi-static scenes)
    """

    sigma_a: float = 5.0
    sigma_alpha: float = 50.0
    lambda_v: float = 0.9


@dataclass
class ParticleState:
    """N particles in the base frame (module docstring for units)."""

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    omega: np.ndarray
    lw: np.ndarray

    @property
    def n(self) -> int:
        return len(self.p)

    def copy(self) -> "ParticleState":
        return ParticleState(self.p.copy(), self.v.copy(), self.q.copy(), self.omega.copy(), self.lw.copy())

    def take(self, ancestors: np.ndarray) -> "ParticleState":
        """The resampled state: particles ``ancestors`` (N,) copied, weights reset to uniform."""
        return ParticleState(self.p[ancestors], self.v[ancestors], self.q[ancestors], self.omega[ancestors],
                             uniform_log_weights(len(ancestors)))

    def poses(self) -> np.ndarray:
        """(N, 4, 4) T_base_bone of the particles: se3.from_quat_trans(q, p), written out (per frame;
        the same values to the bit, tests/test_estimate_fast.py)."""
        w, x, y, z = self.q[:, 0], self.q[:, 1], self.q[:, 2], self.q[:, 3]
        T = np.zeros((len(self.q), 4, 4))
        T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
        T[:, :3, 3] = self.p
        T[:, 3, 3] = 1.0
        return T


def predict_position(state: ParticleState, dt: float, params: MotionParams,
                     rng: np.random.Generator) -> ParticleState:
    """Propagate (p, v) one step of ΔT = ``dt`` seconds; (q, ω, lw) are kept. Returns a new state."""
    w_p = rng.normal(0.0, params.sigma_a, state.p.shape)
    p = state.p + dt * state.v + 0.5 * dt * dt * w_p
    v = params.lambda_v * state.v + dt * w_p
    return replace(state, p=p, v=v)


def predict_orientation(state: ParticleState, dt: float, params: MotionParams,
                        rng: np.random.Generator) -> ParticleState:
    """Propagate (ω, q) one step: ω ← λ_v ω + ΔT w_ω, q ← exp(ΔT ω) ⊗ q (base-frame rate)."""
    w_omega = rng.normal(0.0, params.sigma_alpha, state.omega.shape)
    omega = params.lambda_v * state.omega + dt * w_omega
    q = _rotate_left(dt * omega, state.q)
    # keep unit norm against the drift of repeated products
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return replace(state, q=q, omega=omega)


def _rotate_left(rotvec: np.ndarray, q: np.ndarray) -> np.ndarray:
    """quat.multiply(quat.exp_map(rotvec), q) for (N, 3) and (N, 4), written out (per frame; the same
    values to the bit, tests/test_estimate_fast.py)."""
    angle = np.linalg.norm(rotvec, axis=-1)
    half = 0.5 * angle
    small = angle < quat._SMALL
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    w1, x1, y1, z1 = np.cos(half), k * rotvec[:, 0], k * rotvec[:, 1], k * rotvec[:, 2]
    w2, x2, y2, z2 = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out = np.empty((len(q), 4))
    out[:, 0] = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    out[:, 1] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    out[:, 2] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    out[:, 3] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    return out


def predict(state: ParticleState, dt: float, params: MotionParams, rng: np.random.Generator) -> ParticleState:
    """The full transition: position block, then orientation block (independent noises)."""
    return predict_orientation(predict_position(state, dt, params, rng), dt, params, rng)


def perturb_orientations(q: np.ndarray, sigma_r: float, rng: np.random.Generator) -> np.ndarray:
    """exp(r) ⊗ q with r ~ N(0, σ_r² I) rotation vectors (base frame, left), (N, 4) -> (N, 4)."""
    r = rng.normal(0.0, sigma_r, (len(q), 3))
    return quat.multiply(quat.exp_map(r), q)


def initialise(T_base_bone: np.ndarray, n: int, sigma_p: float, sigma_r: float,
               rng: np.random.Generator) -> ParticleState:
    """N particles around one pose: p ~ N(t, σ_p² I), q = exp(r) ⊗ q0 with r ~ N(0, σ_r² I).

    Parameters
    ----------
    T_base_bone : (4, 4) the coarse initial pose
    n : number of particles
    sigma_p : m, position spread per axis
    sigma_r : rad, orientation spread per axis (rotation vector, base frame)

    Velocities and angular rates start at zero; weights uniform.
    """
    q0, t0 = se3.to_quat_trans(np.asarray(T_base_bone, dtype=float))
    p = t0 + rng.normal(0.0, sigma_p, (n, 3))
    q = perturb_orientations(np.repeat(q0[None], n, axis=0), sigma_r, rng)
    return ParticleState(p, np.zeros((n, 3)), q, np.zeros((n, 3)), uniform_log_weights(n))


def initialise_from_point(point_base: np.ndarray, q_base_bone: np.ndarray, n: int, sigma_p: float,
                          rng: np.random.Generator, point_bone: np.ndarray | None = None) -> ParticleState:
    """N particles from a position prior on one point of the bone, orientations given.

    Parameters
    ----------
    point_base : (3,) m, the point in the base frame (a surgeon pointing, a click)
    q_base_bone : (4,) one orientation for all, or (n, 4) one per particle (e.g. uniform on SO(3))
    n : number of particles
    sigma_p : m, std per axis of the point's prior N(point, σ_p² I)
    point_bone : (3,) m, the same point in the bone frame (default: the bone frame's origin);
        then p = point - R(q) point_bone so that the particle's copy of the point lands on the draw
    """
    q = np.broadcast_to(np.asarray(q_base_bone, dtype=float), (n, 4)).copy()
    x = np.asarray(point_base, dtype=float) + rng.normal(0.0, sigma_p, (n, 3))
    if point_bone is not None:
        x = x - quat.rotate(q, np.broadcast_to(np.asarray(point_bone, dtype=float), (n, 3)))
    return ParticleState(x, np.zeros((n, 3)), q, np.zeros((n, 3)), uniform_log_weights(n))


def draws_about_centroid(centre: np.ndarray, p0: np.ndarray, q0: np.ndarray, n: int, sigma_p: float,
                         sigma_r: float, rng: np.random.Generator, keep_first: bool = False, every: int = 0):
    """n poses (p, q) about (p0, q0) turned about the bone's centroid ``centre`` (base frame):
    r ~ N(0, σ_r² I), ε ~ N(0, σ_p² I), p' = c + R(r)(p0 - c) + ε, q' = exp(r) ⊗ q0 (app/filter/recovery.py,
    "What": turning about the bone frame's origin would throw the crest centimetres away); with
    ``keep_first`` the first is (p0, q0) itself. ``centre``, ``p0``, ``q0`` are one pose or one per
    draw ((n, 3), (n, 3), (n, 4): many poses' draws in one batch); with ``every`` > 0 (and
    ``keep_first``) each ``every``-th draw from the first is its pose itself."""
    r = rng.normal(0.0, sigma_r, (n, 3))
    eps = rng.normal(0.0, sigma_p, (n, 3))
    if keep_first:
        first = slice(0, n, every) if every > 0 else 0
        r[first], eps[first] = 0.0, 0.0
    dq = quat.exp_map(r)
    c = np.broadcast_to(centre, (n, 3))
    p = c + quat.rotate(dq, np.broadcast_to(p0 - centre, (n, 3))) + eps
    q = quat.normalize(quat.multiply(dq, np.broadcast_to(q0, (n, 4))))
    return p, q
