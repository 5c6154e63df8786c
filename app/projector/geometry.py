"""Plain-numpy geometry for plans and the accuracy checks: rays against meshes, distances.

No GL and no optional packages (trimesh's ray and proximity queries need rtree or embree, which
osteonav does not depend on):

- :func:`ray_mesh_first_hit`: Moeller-Trumbore ray/triangle intersection, vectorised in chunks,
  first hit along each ray (t > 0).
- :func:`closest_points_on_mesh`: nearest point of a mesh to query points; candidate triangles
  from a k-d tree of triangle centroids, then trimesh's exact point-triangle projection.
- :func:`distance_to_polylines`: distance from points to a set of 3D segments.
"""
from __future__ import annotations

import numpy as np

RAY_EPS = 1e-12
MAX_INCIDENCE_DEG = 75.0
"""Surface parts seen more obliquely than this from the projector (angle between the surface normal
and the ray back to the projector) get no line (app/projector/render.py): there a millimetre of light
smears over several millimetres of bone, and a pose error of 0.1 mm moves the line by millimetres
(BENCHMARKS.md §6f: outline points at 80-90 deg landed up to 3.6 mm off at 0.09 mm ADD)."""


def ray_mesh_first_hit(origins: np.ndarray, directions: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                       chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of each ray with a triangle mesh (Moeller & Trumbore 1997).

    Parameters
    ----------
    origins : (N, 3) or (3,) float, ray origins (any frame, metres)
    directions : (N, 3) float, ray directions (need not be unit length)
    vertices : (V, 3) float, faces : (F, 3) int, the mesh in the same frame

    Returns
    -------
    t : (N,) float64, ray parameter of the first hit (point = origin + t * direction); inf = miss
    face : (N,) int64, index of the face hit, -1 = miss
    """
    d = np.atleast_2d(np.asarray(directions, dtype=float))
    o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces)]
    face_ids = np.arange(len(tri))
    if np.ndim(origins) == 1 and len(d):
        face_ids = _faces_in_ray_cone(np.asarray(origins, dtype=float), d, tri)
        tri = tri[face_ids]
    if len(tri) == 0:
        return np.full(len(d), np.inf), np.full(len(d), -1, dtype=np.int64)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    t_out = np.full(len(d), np.inf)
    f_out = np.full(len(d), -1, dtype=np.int64)
    for s in range(0, len(d), chunk):
        dd, oo = d[s:s + chunk, None, :], o[s:s + chunk, None, :]
        p = np.cross(dd, e2[None])
        det = np.einsum("fk,rfk->rf", e1, p)
        ok = np.abs(det) > RAY_EPS
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = oo - v0[None]
        u = np.einsum("rfk,rfk->rf", tv, p) * inv
        q = np.cross(tv, e1[None])
        v = np.einsum("rk,rfk->rf", dd[:, 0], q) * inv
        t = np.einsum("fk,rfk->rf", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = np.where(hit, t, np.inf)
        best = np.argmin(t, axis=1)
        tb = t[np.arange(len(best)), best]
        t_out[s:s + chunk] = tb
        f_out[s:s + chunk] = np.where(np.isfinite(tb), face_ids[best], -1)
    return t_out, f_out


def _faces_in_ray_cone(origin: np.ndarray, d: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Indices of the triangles that rays from one ``origin`` can hit (a conservative pre-filter).

    Vertices are projected centrally onto the plane z = 1 of a frame whose z is the rays' mean
    direction; a triangle entirely in front of the origin whose projected box misses the rays'
    box cannot be hit. Triangles reaching behind the origin are always kept.
    """
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    z = dn.mean(axis=0)
    if np.linalg.norm(z) < 0.5 or np.min(dn @ (z / np.linalg.norm(z))) < 0.2:
        return np.arange(len(tri))   # rays spread too widely for one central projection
    z /= np.linalg.norm(z)
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])          # rows: the cone frame's axes
    rays = dn @ R.T
    ray_xy = rays[:, :2] / rays[:, 2:]
    lo, hi = ray_xy.min(axis=0) - 1e-6, ray_xy.max(axis=0) + 1e-6
    v = (tri - origin) @ R.T                       # (F, 3, 3)
    front = np.all(v[..., 2] > 1e-9, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = v[..., :2] / v[..., 2:]
    tlo, thi = xy.min(axis=1), xy.max(axis=1)
    overlap = np.all((thi >= lo) & (tlo <= hi), axis=1)
    return np.nonzero(~front | overlap)[0]


def closest_points_on_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                           k: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest surface point of a mesh for each query point.

    Candidates are the ``k`` triangles whose centroids are nearest; exact for points near the
    surface of a mesh with even-sized triangles (the use here: checking that a plan lies on the bone).

    Returns
    -------
    closest : (N, 3) float64 points on the mesh; distance : (N,) float64 metres;
    face : (N,) int64 index of the face each closest point lies on
    """
    import trimesh
    from scipy.spatial import cKDTree

    pts = np.atleast_2d(np.asarray(points, dtype=float))
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces)]
    k = min(k, len(tri))
    _, idx = cKDTree(tri.mean(axis=1)).query(pts, k=k)
    idx = np.asarray(idx).reshape(len(pts), k)
    cand = trimesh.triangles.closest_point(tri[idx.ravel()], np.repeat(pts, k, axis=0)).reshape(len(pts), k, 3)
    dist = np.linalg.norm(cand - pts[:, None], axis=2)
    best = np.argmin(dist, axis=1)
    rows = np.arange(len(pts))
    return cand[rows, best], dist[rows, best], idx[rows, best].astype(np.int64)


def distance_to_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """(N,) distance of each point to the nearest of the segments a_j b_j ((M, 3) each), metres."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ab = b - a
    L2 = np.maximum(np.einsum("mk,mk->m", ab, ab), 1e-30)
    out = np.empty(len(pts))
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk, None, :]
        t = np.clip(np.einsum("nmk,mk->nm", p - a[None], ab) / L2, 0.0, 1.0)
        c = a[None] + t[..., None] * ab[None]
        out[s:s + chunk] = np.sqrt(np.min(np.sum((p - c) ** 2, axis=2), axis=1))
    return out


def surface_normals_at(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) unit normal of the mesh face nearest each point (bone frame): the normals the
    projector's ribbons carry (app/projector/render.py ``ribbon_triangles``)."""
    import trimesh

    _, _, face = closest_points_on_mesh(points, vertices, faces)
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).face_normals)[face]


def facing(normals: np.ndarray, points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(N,) |cos| of the angle between each surface normal and the ray from the point back to
    ``origin`` (the projector's centre), all in one frame; the crest is an open surface: either side
    (as projector_line.vert.glsl's ``v_facing``)."""
    back = np.asarray(origin, float)[None] - np.asarray(points, float)
    back /= np.maximum(np.linalg.norm(back, axis=1, keepdims=True), 1e-12)
    n = np.asarray(normals, float)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.abs(np.sum(n * back, axis=1))
