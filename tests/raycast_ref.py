"""An independent numpy reference of the rendered depth: ray casting (Möller-Trumbore).

Not a rasteriser: every pixel centre (u, v) casts the camera ray d = ((u - cx) / fx, (v - cy) / fy, 1)
against each triangle in 3D (Möller & Trumbore 1997: t, β, γ from Cramer's rule on
a + β e1 + γ e2 = t d); a hit needs β >= 0, γ >= 0, β + γ <= 1 and near <= z = t <= far (d_z = 1,
so t is the camera z). Back-face culling keeps triangles with n · d < 0, n = e1 × e2 (the camera
sees their outside). The nearest hit wins. Candidate (triangle, pixel) pairs are limited to the
projected bounding box of triangles in front of the near plane; a triangle crossing it is tested
against every pixel. The backends' conformance tests compare their ``render_depth`` with this and
give the numpy likelihood reference this depth, never the backend's own rendering.
"""
from __future__ import annotations

import numpy as np


def _candidate_pairs(uv_lo, uv_hi):
    """(triangle index, u, v) of every pixel centre in each triangle's inclusive box."""
    nu = np.maximum(uv_hi[:, 0] - uv_lo[:, 0] + 1, 0)
    nv = np.maximum(uv_hi[:, 1] - uv_lo[:, 1] + 1, 0)
    counts = nu * nv
    tri = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    u = uv_lo[tri, 0] + local % nu[tri]
    v = uv_lo[tri, 1] + local // nu[tri]
    return tri, u, v


def raycast_depth(vertices, faces, camera, T_camera_bone, near, far, cull_back_faces) -> np.ndarray:
    """(N, h, w) float64 linear depth of the mesh at each pose (0 = no hit)."""
    out = np.zeros((len(T_camera_bone), camera.height, camera.width))
    for j, T in enumerate(np.asarray(T_camera_bone, dtype=float)):
        out[j] = _raycast_one(np.asarray(vertices, float), np.asarray(faces), camera, T, near, far, cull_back_faces)
    return out


def _raycast_one(vertices, faces, camera, T, near, far, cull):
    w, h = camera.width, camera.height
    p = vertices @ T[:3, :3].T + T[:3, 3]
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    z = np.stack([a[:, 2], b[:, 2], c[:, 2]], axis=1)
    keep = (z >= near).any(axis=1) & ~(z > far).all(axis=1)
    e1, e2 = b - a, c - a
    if cull:
        keep &= np.einsum("ij,ij->i", np.cross(e1, e2), a) < 0   # n · d < 0 ⇔ n · a < 0 for a hit at t > 0
    in_front = (z >= near).all(axis=1)
    zs = np.where(in_front[:, None], z, 1.0)
    tri_xyz = np.stack([a, b, c], axis=1)
    u = camera.fx * tri_xyz[..., 0] / zs + camera.cx
    v = camera.fy * tri_xyz[..., 1] / zs + camera.cy
    lo = np.stack([np.ceil(u.min(1)), np.ceil(v.min(1))], axis=1)
    hi = np.stack([np.floor(u.max(1)), np.floor(v.max(1))], axis=1)
    lo = np.where(in_front[:, None], lo, 0.0)
    hi = np.where(in_front[:, None], hi, [w - 1.0, h - 1.0])
    lo = np.clip(lo, 0, [w, h]).astype(np.int64)
    hi = np.clip(hi, -1, [w - 1, h - 1]).astype(np.int64)
    hi[~keep] = lo[~keep] - 1
    tri, pu, pv = _candidate_pairs(lo, hi)
    d = np.stack([(pu - camera.cx) / camera.fx, (pv - camera.cy) / camera.fy, np.ones(len(pu))], axis=1)
    A, E1, E2 = a[tri], e1[tri], e2[tri]
    pvec = np.cross(d, E2)
    det = np.einsum("ij,ij->i", E1, pvec)
    ok = det != 0
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = -A
    beta = np.einsum("ij,ij->i", tvec, pvec) * inv
    qvec = np.cross(tvec, E1)
    gamma = np.einsum("ij,ij->i", d, qvec) * inv
    t = np.einsum("ij,ij->i", E2, qvec) * inv
    hit = ok & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1) & (t >= near) & (t <= far)
    depth = np.full(h * w, np.inf)
    np.minimum.at(depth, pv[hit] * w + pu[hit], t[hit])
    return np.where(np.isfinite(depth), depth, 0.0).reshape(h, w)
