"""Anterior pelvic plane (APP) and the acetabulum's radiographic inclination and anteversion.

Import as ``from app.marker import pelvic_plane as app_plane``.

**The APP frame P** (right-handed), from three landmarks: the left and right anterior superior
iliac spines (ASIS) and the midpoint of the pubic tubercles (PT)::

    x = (ASIS_left - ASIS_right) / |.|                 patient's left
    y0 = (ASIS_left + ASIS_right) / 2 - PT             cranial, in the plane
    z = x × y0 / |.|                                   anterior, the plane's normal
    y = z × x                                          cranial

The coronal plane of the definitions below is the APP (the pelvis in its APP reference position).

**Radiographic angles** (Murray, J Bone Joint Surg Br 1993;75:228-232) of the acetabular axis a
(unit, pointing out of the acetabulum: lateral, anterior and usually inferior), with
a_P = (a_x, a_y, a_z) its coordinates in P:

- radiographic anteversion RA = asin(a_z): the angle between the axis and the coronal plane,
  positive when the axis points anteriorly;
- radiographic inclination RI = atan2(|a_x|, -a_y): the angle between the longitudinal (cranial-
  caudal) axis and the axis projected onto the coronal plane, 0 when it points straight down, 90°
  when it points straight lateral. |a_x| makes it the same for a left and a right hip.

Hand check: a_P = (±sin 45°, -cos 45°, 0) gives RI = 45°, RA = 0; a_P = (±cos 20° sin 40°,
-cos 20° cos 40°, sin 20°) gives RI = 40°, RA = 20° (:func:`axis_from_angles`).

**Registration with the IMU** (publication C): the marker box sits on a registration device that
touches the three landmarks, so its marker frame has a known rotation ``R_M_P`` (the device's
construction) to the APP; the plane in any reference frame ``ref`` (the camera, or the IMU's
world) is ``R_ref_P = R_ref_M R_M_P`` (:func:`register_pelvic_plane`).
"""
from __future__ import annotations

import numpy as np


def frame_from_landmarks(asis_left: np.ndarray, asis_right: np.ndarray, pubic: np.ndarray) -> np.ndarray:
    """Rotation R_ref_P of the APP frame from three landmarks.

    Parameters
    ----------
    asis_left, asis_right, pubic : (3,) float, points in a frame ``ref`` (metres)

    Returns
    -------
    (3, 3) rotation whose columns are P's x (left), y (cranial), z (anterior) in ``ref``.
    """
    left, right, pt = (np.asarray(p, float) for p in (asis_left, asis_right, pubic))
    x = left - right
    y0 = 0.5 * (left + right) - pt
    z = np.cross(x, y0)
    if np.linalg.norm(x) < 1e-9 or np.linalg.norm(z) < 1e-12:
        raise ValueError("the three landmarks are collinear or coincide: no plane")
    x /= np.linalg.norm(x)
    z /= np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z])


def register_pelvic_plane(R_ref_M: np.ndarray, R_M_P: np.ndarray | None = None) -> np.ndarray:
    """The APP in frame ``ref`` from the marker box's orientation on the registration device.

    R_ref_M : (3, 3) or (N, 3, 3) marker orientation(s) in ``ref`` while on the device; several
        are averaged (chordal mean: the rotation nearest to their sum).
    R_M_P : (3, 3) the APP in the marker frame, fixed by the device (default identity).
    """
    R = np.asarray(R_ref_M, float)
    if R.ndim == 3:
        U, _, Vt = np.linalg.svd(R.sum(axis=0))
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return R @ (np.eye(3) if R_M_P is None else np.asarray(R_M_P, float))


def radiographic_angles(axis_P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inclination, anteversion) in radians of acetabular axes given in the APP frame.

    axis_P : (..., 3) vectors (normalised here) in P. Returns two arrays of shape (...).
    """
    a = np.asarray(axis_P, float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    inclination = np.arctan2(np.abs(a[..., 0]), 0.0 - a[..., 1])  # 0.0 - : no -0.0 (atan2 would give pi)
    anteversion = np.arcsin(np.clip(a[..., 2], -1.0, 1.0))
    return inclination, anteversion


def axis_from_angles(inclination: float, anteversion: float, side: str = "right") -> np.ndarray:
    """The unit acetabular axis in P with the given radiographic angles (radians); the inverse of
    :func:`radiographic_angles`. ``side``: 'right' (lateral = -x) or 'left' (lateral = +x)."""
    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    lateral = -1.0 if side == "right" else 1.0
    c = np.cos(anteversion)
    return np.array([lateral * c * np.sin(inclination), -c * np.cos(inclination), np.sin(anteversion)])


def fragment_angles(R_ref_P: np.ndarray, R_ref_M: np.ndarray, axis_M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inclination, anteversion), radians, of the fragment whose acetabular axis is ``axis_M``.

    R_ref_P : (3, 3) the registered APP; R_ref_M : (..., 3, 3) marker orientations in the same
    frame ``ref``; axis_M : (3,) the acetabular axis in the marker frame (fixed on the fragment,
    from the plan or from the pre-osteotomy angles).
    """
    a_ref = np.asarray(R_ref_M, float) @ np.asarray(axis_M, float)
    return radiographic_angles(a_ref @ np.asarray(R_ref_P, float))  # a_P = R_ref_P^T a_ref


def axis_in_marker(R_ref_P: np.ndarray, R_ref_M: np.ndarray, inclination: float, anteversion: float,
                   side: str = "right") -> np.ndarray:
    """The acetabular axis in the marker frame from angles known at one instant (e.g. measured on
    the pre-operative CT before the osteotomy): a_M = R_ref_M^T R_ref_P a_P."""
    return np.asarray(R_ref_M, float).T @ np.asarray(R_ref_P, float) @ axis_from_angles(inclination, anteversion, side)
