"""Universal Robots kinematics: standard Denavit-Hartenberg forward kinematics, the camera on the
flange, and joint angles interpolated at a frame's stamp.

Standard DH (UR's published convention): link i transforms by Rz(theta_i) Tz(d_i) Tx(a_i)
Rx(alpha_i), theta_i = q_i; the chain's last frame is the flange (UR's ``tool0``), so
``forward_kinematics(dh, q)`` is ``T_base_flange`` and ``T_base_camera = T_base_flange @
T_flange_camera`` (the hand-eye). Tables: UR's "DH parameters for calculations of kinematics and
dynamics" (e-Series).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_ALPHA_UR = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)


@dataclass(frozen=True, eq=False)
class DHParameters:
    """Standard DH parameters of a 6-joint arm (immutable, arrays stored read-only).

    a : (6,) float64, link lengths along x_i, metres
    d : (6,) float64, link offsets along z_{i-1}, metres
    alpha : (6,) float64, link twists about x_i, radians

    Equal when all three arrays are identical. Raises ValueError naming the field that is not
    6 finite numbers.
    """

    a: np.ndarray
    d: np.ndarray
    alpha: np.ndarray

    def __post_init__(self):
        for name in ("a", "d", "alpha"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (6,) or not np.all(np.isfinite(value)):
                raise ValueError(f"DH parameter '{name}' must be 6 finite numbers, got {getattr(self, name)!r}")
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DHParameters):
            return NotImplemented
        return all(np.array_equal(getattr(self, k), getattr(other, k)) for k in ("a", "d", "alpha"))

    def __hash__(self) -> int:
        return hash((self.a.tobytes(), self.d.tobytes(), self.alpha.tobytes()))

    def to_dict(self) -> dict:
        """``{'a', 'd', 'alpha'}`` as lists, the ``robot.dh`` block of trial.yaml."""
        return {"a": self.a.tolist(), "d": self.d.tolist(), "alpha": self.alpha.tolist()}


def _ur(d1, a2, a3, d4, d5, d6) -> DHParameters:
    return DHParameters(a=np.array([0.0, a2, a3, 0.0, 0.0, 0.0]), d=np.array([d1, 0.0, 0.0, d4, d5, d6]),
                        alpha=np.array(_ALPHA_UR))


UR_MODELS: dict[str, DHParameters] = {
    "ur3e": _ur(0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "ur5e": _ur(0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "ur10e": _ur(0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "ur16e": _ur(0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
}


def dh_from_config(robot: dict) -> DHParameters:
    """DH parameters from a trial's or session's ``robot`` block: ``{model: NAME}`` or ``{dh: {a, d, alpha}}``."""
    if not isinstance(robot, dict):
        raise ValueError(f"'robot' must be a mapping with 'model' or 'dh', got {robot!r}")
    has_model, has_dh = "model" in robot, "dh" in robot
    if has_model == has_dh:
        raise ValueError("'robot' needs exactly one of 'robot.model' (one of "
                         f"{', '.join(UR_MODELS)}) or 'robot.dh' ({{a, d, alpha}}), got {sorted(robot)}")
    if has_model:
        name = str(robot["model"]).lower()
        if name not in UR_MODELS:
            raise ValueError(f"'robot.model' is '{robot['model']}'; known models: {', '.join(UR_MODELS)}, "
                             "or give 'robot.dh' instead")
        return UR_MODELS[name]
    dh = robot["dh"]
    missing = [k for k in ("a", "d", "alpha") if k not in (dh or {})]
    if missing:
        raise ValueError(f"'robot.dh' lacks {', '.join(missing)}: give a, d, alpha (6 numbers each)")
    try:
        return DHParameters(a=np.asarray(dh["a"], dtype=float), d=np.asarray(dh["d"], dtype=float),
                            alpha=np.asarray(dh["alpha"], dtype=float))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"'robot.dh': {exc}") from exc


def forward_kinematics(dh: DHParameters, q: np.ndarray) -> np.ndarray:
    """T_base_flange (..., 4, 4) for joint angles q (..., 6) radians: prod_i Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)."""
    q = np.asarray(q, dtype=float)
    T = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
    for i in range(6):
        ct, st = np.cos(q[..., i]), np.sin(q[..., i])
        ca, sa = np.cos(dh.alpha[i]), np.sin(dh.alpha[i])
        A = np.zeros(q.shape[:-1] + (4, 4))
        A[..., 0, 0], A[..., 0, 1], A[..., 0, 2], A[..., 0, 3] = ct, -st * ca, st * sa, dh.a[i] * ct
        A[..., 1, 0], A[..., 1, 1], A[..., 1, 2], A[..., 1, 3] = st, ct * ca, -ct * sa, dh.a[i] * st
        A[..., 2, 1], A[..., 2, 2], A[..., 2, 3] = sa, ca, dh.d[i]
        A[..., 3, 3] = 1.0
        T = T @ A
    return T


def camera_pose(dh: DHParameters, q: np.ndarray, T_flange_camera: np.ndarray) -> np.ndarray:
    """T_base_camera = FK(q) @ T_flange_camera."""
    return forward_kinematics(dh, q) @ np.asarray(T_flange_camera, dtype=float)


def interpolate_joints(stamps_robot: np.ndarray, q_robot: np.ndarray, stamps_query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles linearly interpolated at the query stamps.

    Parameters
    ----------
    stamps_robot : (M,) float64, seconds, non-decreasing (the joint samples' stamps)
    q_robot : (M, 6) float64, radians, unwrapped joint angles (NaN marks a missing sample)
    stamps_query : (K,) float64, seconds (the frames' stamps, same clock)

    Returns
    -------
    q : (K, 6) float64, radians; rows of invalid queries are NaN
    valid : (K,) bool; False for a query outside [stamps_robot[0], stamps_robot[-1]] or whose
        bracketing samples hold a NaN (reported, not guessed). A query exactly at a sample's
        stamp uses that sample alone.

    Raises
    ------
    ValueError
        For mismatched shapes or decreasing robot stamps.
    """
    t = np.asarray(stamps_robot, dtype=float)
    q = np.asarray(q_robot, dtype=float)
    tq = np.asarray(stamps_query, dtype=float)
    if t.ndim != 1 or q.ndim != 2 or q.shape[0] != t.shape[0] or tq.ndim != 1:
        raise ValueError(f"interpolate_joints expects stamps (M,), q (M, n) and queries (K,), got "
                         f"{t.shape}, {q.shape} and {tq.shape}")
    if np.any(np.diff(t) < 0) or not np.all(np.isfinite(t)):
        raise ValueError("interpolate_joints needs finite, non-decreasing robot stamps")
    out = np.full((len(tq), q.shape[1]), np.nan)
    if len(t) == 0:
        return out, np.zeros(len(tq), dtype=bool)
    inside = (tq >= t[0]) & (tq <= t[-1])
    tin = tq[inside]
    # hi: first sample at or after the query; lo: last sample at or before it. On an exact hit
    # span = 0 and that sample is used alone, so a NaN neighbour does not spoil it.
    hi = np.searchsorted(t, tin, side="left")
    lo = np.searchsorted(t, tin, side="right") - 1
    span = t[hi] - t[lo]
    w = np.where(span > 0, (tin - t[lo]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
    out[inside] = np.where(span[:, None] == 0, q[lo], (1 - w) * q[lo] + w * q[hi])
    valid = inside & np.all(np.isfinite(out), axis=1)
    out[~valid] = np.nan
    return out, valid
