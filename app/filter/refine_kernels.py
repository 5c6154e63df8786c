"""numba kernels of the local refinement (app/filter/refine.py; DESIGN.md "Local refinement and the
estimate's uncertainty").

Import as ``from app.filter import refine_kernels``. Each kernel computes what the numpy reference
path of :class:`app.filter.refine.Refiner` (``backend="numpy"``) computes, in one pass without
temporaries (tests/test_refine_kernels.py compares both on random poses; scripts/refine_calls.py on
the refinement calls of replays of the eight CT crests):

- :func:`zbuffer`: the model's z-buffer on the crop grid (refine.py step 1): the camera-facing
  samples (n·p < 0, z > 0) projected with u = fx x / z + cx, rounded to the grid of step ``stride``,
  the nearest depth per cell, then the empty cells filled by the 3x3 minimum of the buffer (every
  one next to a covered cell, or only those between covered cells: ``ring``);
- :func:`measurements`: the silhouette's usable pixels back-projected, y = z K⁻¹ (u, v, 1) (step 2);
- :func:`nearest`, :func:`nearest_from`: the exact nearest model sample of each point (step 3) on a
  uniform grid of cells (:class:`SampleGrid`): shells of cells at Chebyshev distance r = 0, 1, ...
  around the query's cell are searched until the best distance is at most the query's distance to the
  outside of the searched cube (no point outside it can be nearer) or the cube holds the ball of
  ``radius`` (then j = -1, d = inf: not associated, as the k-d tree's ``distance_upper_bound``);
  shells that the grid's distance transform shows empty are skipped, and so is every cell whose box
  lies further than the best distance so far (which starts at ``radius``, or at a first guess's);
- :func:`neighbours`: each measurement's 8 neighbouring measurements on the crop grid (step 5's
  tissue border);
- :func:`normal_equations`: the robust point-to-plane Gauss-Newton system (step 4-6):
  r_i = n_iᵀ(p_i − x_i), Tukey's w_i = (1 − (r_i/s_i)²)² / σ_i², J_i = [((p_i − c) × n_i)ᵀ, n_iᵀ],
  H = Σ w_i J_iᵀJ_i, g = Σ w_i J_iᵀ r_i;
- :func:`gauss_newton`: the iterations of steps 3-6 on one set of measurements, in the kernel: the
  association (each from the previous iteration's sample), the normal equations, the 6x6 solve
  (H + 10⁻¹² I) δ = −g, T ← T exp(δ)⁻¹ about the centre (:func:`increment_inverse`), and the stopping
  and re-render rules of :meth:`app.filter.refine.Refiner.refine`; it returns to Python only to
  render and measure again;
- :func:`statistics`: step 7 of one association: the confirmed, sharp and behind counts, the noise's
  scale and correlation factor (app/tracking/fit_kernels.py) and the moments of the count the noise
  puts behind the model (app/filter/behind_noise.py, with Φ in Cephes' form, :func:`_ndtr`).

Numbers: float64, ``fastmath=False`` (results equal to the numpy path up to summation order); the
kernels release the GIL (app/render/cpu_raster.py ``_njit``), so a refinement can run beside other work
in another thread.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from app.render.cpu_raster import _njit
from app.tracking import fit_kernels

SQRT1_2 = math.sqrt(0.5)

GAP_SLACK = 1e-9   # m: a cell nearer than the best distance by less than this is opened all the same (:func:`_axis_gap`)


@dataclass
class SampleGrid:
    """The model samples sorted by a uniform grid of cubic cells (bone frame).

    points, normals : (S, 3) sorted by cell; index : (S,) the original sample index of each;
    start : (C + 1,) cell c holds points[start[c]:start[c + 1]]; empty : (C,) the chessboard distance
    (in cells) from each cell to the nearest cell that holds a point (shells nearer are empty); origin (3,); cell (m);
    dims (3,) int64 cells per axis (x fastest: c = ix + dims0 (iy + dims1 iz)).
    """

    points: np.ndarray
    normals: np.ndarray
    index: np.ndarray
    start: np.ndarray
    empty: np.ndarray
    origin: np.ndarray
    cell: float
    dims: np.ndarray


def build_grid(points: np.ndarray, normals: np.ndarray, cell: float, max_cells: int = 4_000_000) -> SampleGrid:
    """Sort ``points`` (S, 3) into cells of ``cell`` metres (grown until the grid has <= max_cells)."""
    points = np.asarray(points, float)
    lo, hi = points.min(axis=0), points.max(axis=0)
    while True:
        dims = (np.floor((hi - lo) / cell).astype(np.int64) + 1)
        if int(np.prod(dims)) <= max_cells:
            break
        cell *= 1.5
    ijk = np.minimum(np.floor((points - lo) / cell).astype(np.int64), dims - 1)
    ids = ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2])
    order = np.argsort(ids, kind="stable")
    start = np.zeros(int(np.prod(dims)) + 1, np.int64)
    np.add.at(start, ids + 1, 1)
    start = np.cumsum(start)
    occupied = (np.diff(start) > 0).reshape(dims[2], dims[1], dims[0])
    empty = ndimage.distance_transform_cdt(~occupied, metric="chessboard").astype(np.int64).ravel()
    return SampleGrid(np.ascontiguousarray(points[order]), np.ascontiguousarray(np.asarray(normals, float)[order]),
                      order.astype(np.int64), start, empty, lo.astype(float), float(cell), dims)


@_njit()
def zbuffer(points, normals, R, t, fx, fy, cx, cy, stride, w_grid, h_grid, ring=False):
    """(zbuf (h, w) with inf where empty, c0, r0) on the crop grid; zbuf.size == 0 when nothing projects."""
    n = points.shape[0]
    cols = np.empty(n, np.int64)
    rows = np.empty(n, np.int64)
    zs = np.empty(n)
    m = 0
    for i in range(n):
        px = R[0, 0] * points[i, 0] + R[0, 1] * points[i, 1] + R[0, 2] * points[i, 2] + t[0]
        py = R[1, 0] * points[i, 0] + R[1, 1] * points[i, 1] + R[1, 2] * points[i, 2] + t[1]
        pz = R[2, 0] * points[i, 0] + R[2, 1] * points[i, 1] + R[2, 2] * points[i, 2] + t[2]
        nx = R[0, 0] * normals[i, 0] + R[0, 1] * normals[i, 1] + R[0, 2] * normals[i, 2]
        ny = R[1, 0] * normals[i, 0] + R[1, 1] * normals[i, 1] + R[1, 2] * normals[i, 2]
        nz = R[2, 0] * normals[i, 0] + R[2, 1] * normals[i, 1] + R[2, 2] * normals[i, 2]
        if not (nx * px + ny * py + nz * pz < 0.0 and pz > 0.0):
            continue
        col = np.round((fx * px / pz + cx) / stride)
        row = np.round((fy * py / pz + cy) / stride)
        if col < 0 or col >= w_grid or row < 0 or row >= h_grid:
            continue
        cols[m], rows[m], zs[m] = np.int64(col), np.int64(row), pz
        m += 1
    if m == 0:
        return np.full((0, 0), np.inf), 0, 0
    c0, c1 = max(cols[:m].min() - 1, 0), min(cols[:m].max() + 2, w_grid)
    r0, r1 = max(rows[:m].min() - 1, 0), min(rows[:m].max() + 2, h_grid)
    zbuf = np.full((r1 - r0, c1 - c0), np.inf)
    for i in range(m):
        if zs[i] < zbuf[rows[i] - r0, cols[i] - c0]:
            zbuf[rows[i] - r0, cols[i] - c0] = zs[i]
    return _fill_holes(zbuf, ring), c0, r0


@_njit()
def _fill_holes(zbuf, ring):
    """Empty cells take the minimum of their 3x3 neighbourhood: with ``ring``, every empty cell next to
    a covered one (the outline grown by a cell all round, scipy's minimum_filter); without, only the
    cells between two covered ones (left and right, above and below, or across either diagonal), the
    outline not grown (refine.py :func:`fill_holes`, the numpy reference)."""
    h, w = zbuf.shape
    out = zbuf.copy()
    for r in range(h):
        for c in range(w):
            if zbuf[r, c] != np.inf:
                continue
            if not ring:
                if r == 0 or c == 0 or r == h - 1 or c == w - 1:
                    continue
                between = ((zbuf[r, c - 1] != np.inf and zbuf[r, c + 1] != np.inf)
                           or (zbuf[r - 1, c] != np.inf and zbuf[r + 1, c] != np.inf)
                           or (zbuf[r - 1, c - 1] != np.inf and zbuf[r + 1, c + 1] != np.inf)
                           or (zbuf[r - 1, c + 1] != np.inf and zbuf[r + 1, c - 1] != np.inf))
                if not between:
                    continue
            best = np.inf
            for rr in range(max(r - 1, 0), min(r + 2, h)):
                for cc in range(max(c - 1, 0), min(c + 2, w)):
                    best = min(best, zbuf[rr, cc])
            out[r, c] = best
    return out


@_njit()
def measurements(depth, zbuf, x0, y0, stride, fx, fy, cx, cy, occluder_margin):
    """(y (M, 3) camera-frame points, z* (M,)) of the crop cells with a model depth and a usable
    measurement (finite, > 0, not an occluder: z >= z* − margin); row-major order like np.nonzero."""
    h = min(zbuf.shape[0], (depth.shape[0] - y0 + stride - 1) // stride)
    w = min(zbuf.shape[1], (depth.shape[1] - x0 + stride - 1) // stride)
    y = np.empty((max(h, 0) * max(w, 0), 3))
    zstar = np.empty(max(h, 0) * max(w, 0))
    m = 0
    for r in range(h):
        v = y0 + r * stride
        for c in range(w):
            zm = zbuf[r, c]
            u = x0 + c * stride
            z = np.float64(depth[v, u])
            if not _usable(zm, z, occluder_margin):
                continue
            y[m, 0] = (u - cx) / fx * z
            y[m, 1] = (v - cy) / fy * z
            y[m, 2] = z
            zstar[m] = zm
            m += 1
    return y[:m], zstar[:m]


@_njit()
def _usable(zm, z, occluder_margin):
    """A crop cell gives a measurement: the model covers it (z* finite) and its depth z is valid and not
    an occluder (z >= z* − margin; refine.py step 2)."""
    return zm != np.inf and np.isfinite(z) and z > 0.0 and z >= zm - occluder_margin


@_njit()
def neighbours(depth, zbuf, x0, y0, stride, occluder_margin):
    """(M, 8) int64: for each of :func:`measurements`' points (same order), the indices of the
    measurements in its 8 neighbouring cells of the crop grid, -1 where that cell has none."""
    h = max(min(zbuf.shape[0], (depth.shape[0] - y0 + stride - 1) // stride), 0)
    w = max(min(zbuf.shape[1], (depth.shape[1] - x0 + stride - 1) // stride), 0)
    index = np.full((h, w), -1, np.int64)
    m = 0
    for r in range(h):
        for c in range(w):
            if not _usable(zbuf[r, c], np.float64(depth[y0 + r * stride, x0 + c * stride]), occluder_margin):
                continue
            index[r, c] = m
            m += 1
    out = np.full((m, 8), -1, np.int64)
    for r in range(h):
        for c in range(w):
            i = index[r, c]
            if i < 0:
                continue
            k = 0
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    if dr == 0 and dc == 0:
                        continue
                    if 0 <= r + dr < h and 0 <= c + dc < w:
                        out[i, k] = index[r + dr, c + dc]
                    k += 1
    return out


@_njit()
def nearest(query, points, start, empty, origin, cell, dims, radius):
    """(j (Q,) index into the grid's sorted points, d (Q,)) of each query's nearest point; d = inf,
    j = -1 where none lies within ``radius`` (module docstring). ``empty`` (C,): shells of cells
    around each cell known to hold no point (:class:`SampleGrid`), skipped."""
    return nearest_from(query, np.full(query.shape[0], -1, np.int64), points, start, empty, origin, cell, dims, radius)


@_njit()
def nearest_from(query, hint, points, start, empty, origin, cell, dims, radius):
    """:func:`nearest` with a first guess per query, ``hint`` (Q,) an index into the grid's points (-1:
    none; the previous Gauss-Newton iteration's association of the same measurement): the search
    starts from its distance, so fewer cells are opened. The result is :func:`nearest`'s unless another
    sample lies at exactly the hint's distance (then either may be returned)."""
    nq = query.shape[0]
    out_j = np.full(nq, -1, np.int64)
    out_d = np.full(nq, np.inf)
    for q in range(nq):
        out_j[q], out_d[q] = _nearest_one(query[q, 0], query[q, 1], query[q, 2], hint[q], points, start, empty, origin,
                                          cell, dims, radius)
    return out_j, out_d


@_njit()
def _nearest_one(qx, qy, qz, hint, points, start, empty, origin, cell, dims, radius):
    """(j, d) of one query (:func:`nearest_from`). A cell whose box lies at least the best distance so far
    from the query is not opened: none of its points could replace the best (the comparison is
    strict), so the result is the one of opening every cell, in the same order. The best distance
    starts just above ``radius`` (1e-12 relative, far more than sqrt's rounding): a point further than
    that would be refused at the end anyway; or at the hint's distance when that is nearer."""
    max_shell = int(math.ceil(radius / cell))
    ix = int(math.floor((qx - origin[0]) / cell))
    iy = int(math.floor((qy - origin[1]) / cell))
    iz = int(math.floor((qz - origin[2]) / cell))
    outside = max(-ix, ix - dims[0] + 1, -iy, iy - dims[1] + 1, -iz, iz - dims[2] + 1, 0)
    if outside == 0:
        first = empty[ix + dims[0] * (iy + dims[1] * iz)]
    else:
        first = outside
    best, best_j = radius * radius * (1.0 + 1e-12), -1
    if hint >= 0:
        dx, dy, dz = points[hint, 0] - qx, points[hint, 1] - qy, points[hint, 2] - qz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best:
            best, best_j = d2, hint
    for r in range(first, max_shell + 1):
        for cz in range(max(iz - r, 0), min(iz + r + 1, dims[2])):
            gz = _axis_gap(qz, origin[2], cell, cz)
            if gz * gz >= best:
                continue
            for cy in range(max(iy - r, 0), min(iy + r + 1, dims[1])):
                gy = _axis_gap(qy, origin[1], cell, cy)
                gzy = gz * gz + gy * gy
                if gzy >= best:
                    continue
                on_face = abs(cz - iz) == r or abs(cy - iy) == r
                step = 1 if on_face else 2 * r
                cx = ix - r
                while cx <= ix + r:
                    if 0 <= cx < dims[0]:
                        gx = _axis_gap(qx, origin[0], cell, cx)
                        if gzy + gx * gx < best:
                            c = cx + dims[0] * (cy + dims[1] * cz)
                            for k in range(start[c], start[c + 1]):
                                dx, dy, dz = points[k, 0] - qx, points[k, 1] - qy, points[k, 2] - qz
                                d2 = dx * dx + dy * dy + dz * dz
                                if d2 < best:
                                    best, best_j = d2, k
                    cx += max(step, 1)
        if best_j >= 0 and math.sqrt(best) <= _cube_clearance(qx, qy, qz, ix, iy, iz, r, origin, cell):
            break
    if best_j >= 0 and math.sqrt(best) <= radius:
        return best_j, math.sqrt(best)
    return -1, np.inf


@_njit()
def _axis_gap(q, origin, cell, i):
    """Distance along one axis from the coordinate ``q`` to the slab of cell ``i`` (0 inside it), less
    ``GAP_SLACK`` so that rounding (of the slab's bounds, of a point's cell) can only open a cell more,
    never less."""
    lo = origin + i * cell
    hi = lo + cell
    if q < lo:
        return max(lo - q - GAP_SLACK, 0.0)
    if q > hi:
        return max(q - hi - GAP_SLACK, 0.0)
    return 0.0


@_njit()
def gather(j, points, normals):
    """(x, n) (Q, 3): the samples and normals of :func:`nearest`'s indices ``j``; NaN where j = -1."""
    x = np.full((j.shape[0], 3), np.nan)
    n = np.full((j.shape[0], 3), np.nan)
    for q in range(j.shape[0]):
        if j[q] >= 0:
            for a in range(3):
                x[q, a] = points[j[q], a]
                n[q, a] = normals[j[q], a]
    return x, n


@_njit()
def _cube_clearance(qx, qy, qz, ix, iy, iz, r, origin, cell):
    """Distance from the query to the outside of the cube of cells within r of its cell: no point
    outside the searched cube can be nearer than this (>= r · cell)."""
    lo_x, lo_y, lo_z = origin[0] + (ix - r) * cell, origin[1] + (iy - r) * cell, origin[2] + (iz - r) * cell
    hi_x, hi_y, hi_z = lo_x + (2 * r + 1) * cell, lo_y + (2 * r + 1) * cell, lo_z + (2 * r + 1) * cell
    return min(qx - lo_x, hi_x - qx, qy - lo_y, hi_y - qy, qz - lo_z, hi_z - qz)


@_njit()
def normal_equations(p, x, n, d, sigma, in_front, center, width, tukey_c, front_sigmas, nbrs):
    """(H (6, 6), g (6,), used, Σ w σ² r², Σ w σ²) of the robust GN system (module docstring); a pair is
    used when |r| < s, d < 3 s and the measurement is not buried (z* − z <= max(front σ, width)),
    s = max(tukey_c σ, width), and, with ``nbrs`` ((M, 8) from :func:`neighbours`; (0, 8) for none),
    when none of its neighbouring measurements is buried (the tissue's border)."""
    buried = np.empty(p.shape[0], np.bool_)
    for i in range(p.shape[0]):
        buried[i] = in_front[i] > max(front_sigmas * sigma[i], width)
    border = nbrs.shape[0] == p.shape[0]
    H = np.zeros((6, 6))
    g = np.zeros(6)
    used = 0
    num, den = 0.0, 0.0
    J = np.empty(6)
    for i in range(p.shape[0]):
        s = max(tukey_c * sigma[i], width)
        r = n[i, 0] * (p[i, 0] - x[i, 0]) + n[i, 1] * (p[i, 1] - x[i, 1]) + n[i, 2] * (p[i, 2] - x[i, 2])
        if not (abs(r) < s and d[i] < 3.0 * s) or buried[i]:
            continue
        if border:
            beside = False
            for k in range(8):
                if nbrs[i, k] >= 0 and buried[nbrs[i, k]]:
                    beside = True
            if beside:
                continue
        u = r / s
        w = (1.0 - u * u) ** 2 / sigma[i] ** 2
        ax, ay, az = p[i, 0] - center[0], p[i, 1] - center[1], p[i, 2] - center[2]
        J[0] = ay * n[i, 2] - az * n[i, 1]
        J[1] = az * n[i, 0] - ax * n[i, 2]
        J[2] = ax * n[i, 1] - ay * n[i, 0]
        J[3], J[4], J[5] = n[i, 0], n[i, 1], n[i, 2]
        for a in range(6):
            g[a] += w * J[a] * r
            for b in range(a, 6):
                H[a, b] += w * J[a] * J[b]
        num += w * sigma[i] ** 2 * r * r
        den += w * sigma[i] ** 2
        used += 1
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, used, num, den


@_njit()
def to_bone(y, T):
    """p = T⁻¹ y (M, 3): camera-frame points into the bone frame, T⁻¹ = [Rᵀ, −Rᵀ t] (refine.py step 2)."""
    p = np.empty_like(y)
    tx = -(T[0, 0] * T[0, 3] + T[1, 0] * T[1, 3] + T[2, 0] * T[2, 3])
    ty = -(T[0, 1] * T[0, 3] + T[1, 1] * T[1, 3] + T[2, 1] * T[2, 3])
    tz = -(T[0, 2] * T[0, 3] + T[1, 2] * T[1, 3] + T[2, 2] * T[2, 3])
    for i in range(y.shape[0]):
        p[i, 0] = y[i, 0] * T[0, 0] + y[i, 1] * T[1, 0] + y[i, 2] * T[2, 0] + tx
        p[i, 1] = y[i, 0] * T[0, 1] + y[i, 1] * T[1, 1] + y[i, 2] * T[2, 1] + ty
        p[i, 2] = y[i, 0] * T[0, 2] + y[i, 1] * T[1, 2] + y[i, 2] * T[2, 2] + tz
    return p


@_njit()
def increment_inverse(delta, center):
    """exp(δ)⁻¹ (4, 4) for δ = (ω, v) applied about the model's centre c (refine.py step 6):
    exp(δ) maps p ↦ c + R (p − c) + v with R = exp([ω]ₓ) from the unit quaternion
    (cos(|ω|/2), ω/|ω| sin(|ω|/2)) (app/geometry/quaternion.py ``exp_map``, ``to_matrix``); its inverse
    is [Rᵀ, −Rᵀ t] with t = v + c − R c."""
    wx, wy, wz = delta[0], delta[1], delta[2]
    angle = math.sqrt(wx * wx + wy * wy + wz * wz)
    half = 0.5 * angle
    if angle < 1e-8:                       # quaternion._SMALL: sin(|ω|/2)/|ω| by its series
        k = 0.5 - angle ** 2 / 48.0
    else:
        k = math.sin(half) / angle
    w, x, y, z = math.cos(half), k * wx, k * wy, k * wz
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    t = np.empty(3)
    for a in range(3):
        t[a] = delta[3 + a] + (center[a] - (R[a, 0] * center[0] + R[a, 1] * center[1] + R[a, 2] * center[2]))
    M = np.zeros((4, 4))
    for a in range(3):
        for b in range(3):
            M[a, b] = R[b, a]
        M[a, 3] = -(R[0, a] * t[0] + R[1, a] * t[1] + R[2, a] * t[2])
    M[3, 3] = 1.0
    return M


@_njit()
def _matmul4(A, B):
    C = np.zeros((4, 4))
    for a in range(4):
        for b in range(4):
            s = 0.0
            for k in range(4):
                s += A[a, k] * B[k, b]
            C[a, b] = s
    return C


GN_DONE, GN_DECLINED, GN_STOPPED, GN_RERENDER = 0, 1, 2, 3


@_njit()
def gauss_newton(y, sigma, in_front, nbrs, T, it0, iterations, start_width, center,
                 points, normals, start, empty, origin, cell, dims,
                 pair_radius, pair_widths, tukey_c, front_sigmas, min_points,
                 stop_rotation, stop_translation, rerender_step, render_lever):
    """The Gauss-Newton iterations ``it0`` .. ``iterations`` − 1 of refine.py (steps 3-6) on one set of
    measurements y (M, 3) (camera frame; σ(z_i), z*_i − z_i and the tissue border's neighbours with
    them), from T = T_camera_bone (4, 4). Each iteration: the Tukey width w = start_width 2^−it;
    p_i = T⁻¹ y_i; the nearest sample x_i, n_i within max(pair_radius, pair_widths w) (:func:`nearest`);
    H = Σ w_i J_iᵀJ_i, g = Σ w_i J_iᵀ r_i (:func:`normal_equations`); (H + 10⁻¹² I) δ = −g; T ← T exp(δ)⁻¹.

    Returns (T, H, used, rms, state, it, p, x, n, d): ``state`` GN_DECLINED (fewer than ``min_points``
    pairs: T, p... of before the step; H, used of the declined system, rms NaN), GN_STOPPED (a step
    under ``stop_rotation`` / ``stop_translation``: ``it`` is the last iteration, and p, x, n, d its
    association), GN_RERENDER (a step that moved the model more than ``rerender_step``, the rotation
    at ``render_lever``: the caller measures again and goes on at ``it``), or GN_DONE (no iteration
    left). The numpy reference is the loop of :meth:`app.filter.refine.Refiner.refine`."""
    H = np.zeros((6, 6))
    used, rms = 0, np.nan
    p = np.empty((0, 3))
    x = np.empty((0, 3))
    n = np.empty((0, 3))
    d = np.empty(0)
    j = np.full(y.shape[0], -1, np.int64)
    for it in range(it0, iterations):
        width = start_width * 0.5 ** it
        p = to_bone(y, T)
        j, d = nearest_from(p, j, points, start, empty, origin, cell, dims, max(pair_radius, pair_widths * width))
        x, n = gather(j, points, normals)
        H, g, used, num, den = normal_equations(p, x, n, d, sigma, in_front, center, width, tukey_c, front_sigmas, nbrs)
        if used < min_points:
            return T, H, used, np.nan, GN_DECLINED, it, p, x, n, d
        A = H.copy()
        for a in range(6):
            A[a, a] += 1e-12
        delta = -np.linalg.solve(A, g)
        rms = math.sqrt(num / max(den, 1e-30))
        T = _matmul4(T, increment_inverse(delta, center))
        step_r = math.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
        step_t = math.sqrt(delta[3] ** 2 + delta[4] ** 2 + delta[5] ** 2)
        if step_r < stop_rotation and step_t < stop_translation:
            return T, H, used, rms, GN_STOPPED, it, p, x, n, d
        if step_r * render_lever > rerender_step or step_t > rerender_step:
            return T, H, used, rms, GN_RERENDER, it + 1, p, x, n, d
    return T, H, used, rms, GN_DONE, iterations, p, x, n, d


@_njit()
def _ndtr(a):
    """Φ(a), the standard normal CDF, as scipy.special.ndtr computes it (Cephes: 0.5 + 0.5 erf(a/√2)
    near 0, 0.5 erfc(|a|/√2) in the tails)."""
    x = a * SQRT1_2
    z = abs(x)
    if z < SQRT1_2:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0 else y


@_njit()
def statistics(y, p, x, n, d, sigma, T, confirm_sigmas, sharp_sigmas, behind_sigmas, stride, fx, fy, cx, cy, window):
    """The statistics of one association (refine.py steps 7-8; the numpy reference is
    ``Refiner._result``): (confirmed, sharp, behind, σ̂_n, f, Σ e_i, Σ e_i (1 − e_i)) with
    confirmed = #{d_i < confirm_sigmas σ_i}, sharp = #{d_i < sharp_sigmas σ_i} / M, behind =
    #{r_i < −behind_sigmas σ_i} / M (r_i = n_iᵀ(p_i − x_i); an unassociated point, NaN, counts as
    neither), (σ̂_n, f) from :func:`app.tracking.fit_kernels.residual_noise`, and the moments of the
    count the noise alone puts behind, e_i = Φ(−behind_sigmas σ_i / (σ̂_n |cos θ_i|)) with θ_i the ray's
    angle to the normal (app/filter/behind_noise.py ``behind_moments``; NaN when σ̂_n is unknown)."""
    m = p.shape[0]
    cbx = -(T[0, 0] * T[0, 3] + T[1, 0] * T[1, 3] + T[2, 0] * T[2, 3])      # the camera's centre, bone frame
    cby = -(T[0, 1] * T[0, 3] + T[1, 1] * T[1, 3] + T[2, 1] * T[2, 3])
    cbz = -(T[0, 2] * T[0, 3] + T[1, 2] * T[1, 3] + T[2, 2] * T[2, 3])
    camera_bone = np.array([cbx, cby, cbz])
    r = np.empty(m)
    confirmed, sharp, behind = 0, 0, 0
    for i in range(m):
        r[i] = n[i, 0] * (p[i, 0] - x[i, 0]) + n[i, 1] * (p[i, 1] - x[i, 1]) + n[i, 2] * (p[i, 2] - x[i, 2])
        confirmed += d[i] < confirm_sigmas * sigma[i]
        sharp += d[i] < sharp_sigmas * sigma[i]
        behind += r[i] < -behind_sigmas * sigma[i]
    noise, factor = fit_kernels.residual_noise(y, p, n, r, camera_bone, stride, fx, fy, cx, cy, sigma, window)
    mean, var = np.nan, np.nan
    if np.isfinite(noise) and m > 0:
        mean, var = 0.0, 0.0
        for i in range(m):
            rx, ry, rz = p[i, 0] - cbx, p[i, 1] - cby, p[i, 2] - cbz
            cos = abs(n[i, 0] * rx + n[i, 1] * ry + n[i, 2] * rz) / math.sqrt(rx * rx + ry * ry + rz * rz)
            if not np.isfinite(cos):
                continue                                    # not associated: e = 0
            scale = noise * max(cos, 1e-6)
            e = _ndtr(-(behind_sigmas * sigma[i]) / scale) if scale > 0 else 0.0   # σ̂_n = 0: nothing behind
            mean += e
            var += e * (1.0 - e)
    return confirmed, sharp / m, behind / m, noise, factor, mean, var
