"""Numba kernels of the CPU likelihood backend: an exact z-buffer rasteriser fused with the pixel term.

Import as ``from app.render import cpu_raster``; the backend class is
:class:`app.render.cpu_likelihood.CPULikelihoodBackend`. All numba code lives in this one module:
numba's on-disk cache (``cache=True``) is invalidated per source file, so a kernel calling a
function of another module could run a stale copy of it after an edit.

Rasterisation, with the GL renderer's conventions (``batched.py``, ``depth.vert.glsl``,
:meth:`PinholeCamera.opengl_projection`):

- a pixel (u, v) is sampled at its centre, the OpenCV image point (u, v); a vertex p (camera
  frame, metres) projects to (fx x / z + cx, fy y / z + cy);
- a triangle covers the pixel when the three screen-space barycentrics of the centre are >= 0
  (edges are inclusive; GL's tie rule differs only for centres exactly on an edge);
- the pixel's depth is the perspective-correct interpolation of the camera z, exactly as GL
  interpolates ``v_depth``: 1 / z = Σ_k b_k / z_k (screen-space barycentrics b_k);
- clipping: triangles are clipped against the near plane z = near in the camera frame
  (Sutherland-Hodgman, then a fan), pixels farther than ``far`` are dropped (GL clips both in clip
  space, which gives the same pixels), and the image border is the tile border;
- back-face culling (optional, for meshes wound counter-clockwise seen from outside): a triangle is
  culled when its normal n = (b - a) × (c - a) has n · a >= 0 in the camera frame, which is GL's
  ``front_face = ccw`` in its y-up window after the OpenCV -> OpenGL flip;
- the z-buffer keeps the nearest depth; 0 means "not covered".

The pixel term is :func:`app.filter.likelihood_ref.pixel_log_likelihood` in float64 (every
option: beam / classification with L0, exponential / smooth exponential occlusion ((B) eq. 4.33),
background ratio with the occluder margin, α tempering or the pixel-count regularisation (B) eq.
4.37), packed into a float64 vector by :func:`pack_params`; without classification the logs are
summed as the log of a running product of the pixels' densities (:func:`_score_and_clear`).

Parallelism: ``prange`` over chunks, each owning one z-buffer, read and cleared only inside the
pixel box of the pose's projected vertices; the chunks take the hypotheses one at a time from a
shared counter (:func:`_take_next`, an atomic add), so a thread that gets less of a core (the stage
worker's refinement beside it, app/pipeline/stages.py) takes fewer of them: numba's ``prange`` itself
hands its iterations out statically, half to each thread. Every hypothesis is scored alone, so
which chunk takes it changes no bit of ``out_ll``.
"""
from __future__ import annotations

import logging
import math
import os

# Threads of numba's OpenMP layer sleep while waiting instead of spinning: on a loaded machine a
# spinning barrier waits for a descheduled thread (measured on the 2-core CI machine, 4 loaded:
# 2.2 ms per parallel launch spinning, 11 us passive). Read when libgomp loads; set it to override.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402 (after OMP_WAIT_POLICY)
import numpy as np
from numba import prange
from numba.core import cgutils, types
from numba.extending import intrinsic

from app.filter.likelihood_ref import LOG_FLOOR, LikelihoodParams

log = logging.getLogger(__name__)

N_PARAMS = 17
_PRODUCT_RANGE = 1e150   # :func:`_score_and_clear` keeps its running product in [1 / this, this]
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_SQRT1_2 = 1.0 / math.sqrt(2.0)


def _njit(parallel: bool = False, inline: str = "never"):
    """``numba.njit(cache=True, fastmath=False, nogil=True)``; without a writable cache location (a
    read-only package directory and no usable NUMBA_CACHE_DIR or user cache) the kernel compiles
    uncached. ``nogil``: a kernel releases the GIL, so a search on the worker thread
    (app/tracking/search_worker.py) and the frame loop run side by side. ``inline="always"``: numba
    inlines the function into its callers (no call with its array arguments per use: for the
    per-face rasteriser, 8 % of the likelihood kernel's CPU; BENCHMARKS.md "Filter rate and CPU")."""
    def wrap(fn):
        try:
            return numba.njit(parallel=parallel, fastmath=False, cache=True, nogil=True, inline=inline)(fn)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
            log.warning("numba cannot cache %s (%s); it compiles on every start. Set NUMBA_CACHE_DIR "
                        "to a writable folder to cache it", fn.__name__, exc)
            return numba.njit(parallel=parallel, fastmath=False, cache=False, nogil=True, inline=inline)(fn)
    return wrap


def pack_params(p: LikelihoodParams) -> np.ndarray:
    """The likelihood parameters as the kernels' float64 vector (order fixed by :data:`N_PARAMS`);
    [16]: sum by products (no classification, p_u >= LOG_FLOOR: every density is above the floor)."""
    p_u = p.w_u / p.z_max
    product = not p.classification and p_u >= LOG_FLOOR
    return np.array([p.z_max, p.lam, p.w_u, p.w_e, p.w_n, p.k, p.sigma_base, p.l0_weight, p.pixel_count_reg,
                     p.pixel_weight, p.occluder_margin, float(p.occlusion == "smooth_exponential"),
                     float(bool(p.classification)), float(bool(p.background_ratio)),
                     math.log(p.z_max), math.log(max(p_u, LOG_FLOOR)), float(product)], dtype=np.float64)


# ---------------------------------------------------------------- the threads' shared counter

@intrinsic
def _fetch_add(typingctx, counter, value):
    """``counter[0] += value`` as one atomic read-modify-write; returns the value before (int64).
    ``counter``: a 1-d int64 array shared by a ``prange``'s threads."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1):
        return None
    sig = types.int64(counter, types.int64)

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, signature.args[0], array, [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", ptr, args[1], "monotonic")

    return sig, codegen


@_njit(inline="always")
def _take_next(counter):
    """The next hypothesis index for a chunk of :func:`batch` (all taken: >= N)."""
    return _fetch_add(counter, 1)


# ---------------------------------------------------------------- rasterisation

@_njit()
def _min3(a, b, c):
    """min(a, b, c) for finite floats, written out: numba's 3-argument builtin is slower here."""
    m = a if a < b else b
    return m if m < c else c


@_njit()
def _max3(a, b, c):
    """max(a, b, c) for finite floats, written out (see :func:`_min3`)."""
    m = a if a > b else b
    return m if m > c else c


@_njit(inline="always")
def _signed_area(ua, va, ub, vb, uc, vc):
    """Twice the projected triangle's signed area (pixel units; >= 0: facing away, :func:`_render_one`)."""
    return (ub - ua) * (vc - va) - (uc - ua) * (vb - va)


@_njit(inline="always")
def _drawn(area, cull):
    """Whether a triangle of signed area ``area`` (:func:`_signed_area`) is drawn: not flat, and facing
    the camera when ``cull``."""
    return not (area == 0.0 or (cull and area > 0.0))


@_njit(inline="always")
def _span(a, b, c, size):
    """(lo, hi): the pixel centres 0 .. size - 1 between min(a, b, c) and max(a, b, c) (lo > hi: none)."""
    return max(math.ceil(_min3(a, b, c)), 0), min(math.floor(_max3(a, b, c)), size - 1)


@_njit(inline="always")
def _raster_triangle(ua, va, iza, ub, vb, izb, uc, vc, izc, cam, cull, zbuf):
    """Z-buffer one projected triangle (pixel coordinates u, v and 1 / z of its vertices, all with
    z >= near); with ``cull`` a triangle of area >= 0 (n · a >= 0: facing away) is skipped."""
    area = _signed_area(ua, va, ub, vb, uc, vc)
    if not _drawn(area, cull):
        return
    h, w = zbuf.shape
    i_u0, i_u1 = _span(ua, ub, uc, w)
    i_v0, i_v1 = _span(va, vb, vc, h)
    if i_u0 > i_u1 or i_v0 > i_v1:
        return
    _fill_triangle(ua, va, iza, ub, vb, izb, uc, vc, izc, area, i_u0, i_u1, i_v0, i_v1, cam, zbuf)


@_njit(inline="always")
def _fill_triangle(ua, va, iza, ub, vb, izb, uc, vc, izc, area, i_u0, i_u1, i_v0, i_v1, cam, zbuf):
    """:func:`_raster_triangle`'s pixels: the centres (u, v) of the box [i_u0, i_u1] x [i_v0, i_v1]
    inside the triangle of signed area ``area`` (drawn, :func:`_drawn`) whose depth z is within the
    clip planes and nearer than the z-buffer's (0: empty)."""
    # barycentrics as affine functions of the pixel centre: b_k = (C_k + A_k u + B_k v) / area
    inv_area = 1.0 / area
    a_a, b_a, c_a = (vb - vc) * inv_area, (uc - ub) * inv_area, (ub * vc - uc * vb) * inv_area
    a_b, b_b, c_b = (vc - va) * inv_area, (ua - uc) * inv_area, (uc * va - ua * vc) * inv_area
    a_c, b_c, c_c = (va - vb) * inv_area, (ub - ua) * inv_area, (ua * vb - ub * va) * inv_area
    near_lo, far = cam[4] * (1.0 - 1e-12), cam[5]
    for v in range(i_v0, i_v1 + 1):
        fv = float(v)
        row_a, row_b, row_c = c_a + b_a * fv, c_b + b_b * fv, c_c + b_c * fv
        for u in range(i_u0, i_u1 + 1):
            fu = float(u)
            wa, wb, wc = row_a + a_a * fu, row_b + a_b * fu, row_c + a_c * fu
            # branch-free (the branches of ~1-pixel triangles mispredict): the tests of
            # "skip if wa < 0 or wb < 0 or wc < 0 or z > far or z < near', keep the nearer" as one mask
            den = wa * iza + wb * izb + wc * izc          # 0 where the camera lies in the face's plane
            z = 1.0 / den if den != 0.0 else math.inf      # (numba raises on 1 / 0): never kept
            current = zbuf[v, u]
            keep = ((not wa < 0.0) & (not wb < 0.0) & (not wc < 0.0) & (not z > far) & (not z < near_lo)
                    & ((current <= 0.0) | (z < current)))
            zbuf[v, u] = z if keep else current


@_njit()
def _raster_camera_triangle(x0, y0, z0, x1, y1, z1, x2, y2, z2, cam, cull, zbuf):
    """Project a triangle given in the camera frame (z >= near) and z-buffer it."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    _raster_triangle(fx * x0 / z0 + cx, fy * y0 / z0 + cy, 1.0 / z0, fx * x1 / z1 + cx, fy * y1 / z1 + cy, 1.0 / z1,
                     fx * x2 / z2 + cx, fy * y2 / z2 + cy, 1.0 / z2, cam, cull, zbuf)


@_njit()
def _clip_near(p, i0, i1, i2, near, poly):
    """Sutherland-Hodgman: the part of triangle (p[i0], p[i1], p[i2]) with z >= near into ``poly``
    (up to 4 rows); returns the vertex count (0, 3 or 4)."""
    idx = (i0, i1, i2)
    n = 0
    for k in range(3):
        a, b = idx[k], idx[(k + 1) % 3]
        a_in, b_in = p[a, 2] >= near, p[b, 2] >= near
        if a_in:
            poly[n, 0], poly[n, 1], poly[n, 2] = p[a, 0], p[a, 1], p[a, 2]
            n += 1
        if a_in != b_in:
            t = (near - p[a, 2]) / (p[b, 2] - p[a, 2])
            for d in range(3):
                poly[n, d] = p[a, d] + t * (p[b, d] - p[a, d])
            poly[n, 2] = near
            n += 1
    return n


@_njit()
def _render_one(T, vertices, faces, cam, cull, p, poly, zbuf, box):
    """Z-buffer the mesh at pose T (camera <- bone) into ``zbuf`` (all 0 on entry); ``box`` gets an
    inclusive pixel box (u0, v0, u1, v1) that holds every written pixel (empty: u1 < u0): the
    projected vertices' bounding box, or the whole image when a vertex lies before the near plane.

    ``p`` (V, 6) scratch: camera-frame x, y, z and, for z >= near, pixel u, v and 1 / z per vertex.
    Culling compares the projected area's sign: for vertices in front of the camera
    sign(area) = sign(det[a, b, c]) = sign(n · a); a clipped triangle uses n · a itself.
    """
    fx, fy, cx, cy, near, far = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5]
    u_min, v_min, u_max, v_max = np.inf, np.inf, -np.inf, -np.inf
    # the pose's entries in locals: numba reloaded T's 12 entries for every vertex (the stores into
    # ``p`` may alias T as far as it knows); the same arithmetic, in the same order
    t00, t01, t02, t03 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    t10, t11, t12, t13 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    t20, t21, t22, t23 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    for i in range(vertices.shape[0]):
        vx, vy, vz = vertices[i, 0], vertices[i, 1], vertices[i, 2]
        x = t00 * vx + t01 * vy + t02 * vz + t03
        y = t10 * vx + t11 * vy + t12 * vz + t13
        z = t20 * vx + t21 * vy + t22 * vz + t23
        p[i, 0], p[i, 1], p[i, 2] = x, y, z
        if z >= near:
            iz = 1.0 / z
            p[i, 3], p[i, 4], p[i, 5] = fx * x * iz + cx, fy * y * iz + cy, iz
            u_min, u_max = min(u_min, p[i, 3]), max(u_max, p[i, 3])
            v_min, v_max = min(v_min, p[i, 4]), max(v_max, p[i, 4])
        else:                                   # clipped triangles can reach anywhere
            u_min, v_min, u_max, v_max = -np.inf, -np.inf, np.inf, np.inf
    # the box of every pixel centre the projected vertices' hull can cover (conservative)
    h, w = zbuf.shape
    # clamp before rounding: numba's ceil/floor return int64, which cannot hold ±inf
    box[0], box[1] = math.ceil(min(max(u_min, 0.0), w)), math.ceil(min(max(v_min, 0.0), h))
    box[2], box[3] = math.floor(max(min(u_max, w - 1.0), -1.0)), math.floor(max(min(v_max, h - 1.0), -1.0))
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        za, zb, zc = p[a, 2], p[b, 2], p[c, 2]
        if za >= near and zb >= near and zc >= near:
            if za > far and zb > far and zc > far:
                continue
            # _raster_triangle's steps written out: its tests in this loop, before the pixels' code,
            # took 0.84-0.89x the kernel's CPU of the same tests inside the inlined call (a third of
            # the faces are culled, a fifth of the rest hold no pixel centre; BENCHMARKS.md "Filter
            # rate and CPU"); the results are the same bit for bit
            ua, va, ub, vb, uc, vc = p[a, 3], p[a, 4], p[b, 3], p[b, 4], p[c, 3], p[c, 4]
            area = _signed_area(ua, va, ub, vb, uc, vc)
            if not _drawn(area, cull):
                continue
            i_u0, i_u1 = _span(ua, ub, uc, w)
            i_v0, i_v1 = _span(va, vb, vc, h)
            if i_u0 > i_u1 or i_v0 > i_v1:
                continue
            _fill_triangle(ua, va, p[a, 5], ub, vb, p[b, 5], uc, vc, p[c, 5], area, i_u0, i_u1, i_v0, i_v1, cam, zbuf)
        elif za >= near or zb >= near or zc >= near:
            if cull:
                e1x, e1y, e1z = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1], p[b, 2] - p[a, 2]
                e2x, e2y, e2z = p[c, 0] - p[a, 0], p[c, 1] - p[a, 1], p[c, 2] - p[a, 2]
                nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
                if nx * p[a, 0] + ny * p[a, 1] + nz * p[a, 2] >= 0.0:
                    continue
            n = _clip_near(p, a, b, c, near, poly)
            for k in range(1, n - 1):
                _raster_camera_triangle(poly[0, 0], poly[0, 1], poly[0, 2], poly[k, 0], poly[k, 1], poly[k, 2],
                                        poly[k + 1, 0], poly[k + 1, 1], poly[k + 1, 2], cam, False, zbuf)


# ---------------------------------------------------------------- the pixel term (likelihood_ref.py)

@_njit()
def _safe_log(x):
    return math.log(max(x, LOG_FLOOR))


@_njit()
def _normal_cdf(x):
    """Φ(x) = ½ erfc(-x / √2)."""
    return 0.5 * math.erfc(-x * _SQRT1_2)


@_njit()
def _occlusion_density(z, exp_lam_z, z_star, sigma, prm):
    """p_e(z | z*): truncated exponential, or with prm[11] the smooth one of (B) eq. 4.33;
    ``exp_lam_z`` = exp(-λ z), a term of the measured pixel alone (unused by the smooth one)."""
    lam = prm[1]
    if prm[11] != 0.0:
        s2 = lam * sigma * sigma
        window = _normal_cdf((z_star - z + s2) / sigma) - _normal_cdf((s2 - z) / sigma)
        return lam / (1.0 - math.exp(-lam * z_star)) * math.exp(-lam * z + 0.5 * lam * s2) * window
    if z > 0.0 and z < z_star:
        return lam / (1.0 - math.exp(-lam * z_star)) * exp_lam_z
    return 0.0


@_njit()
def pixel_log_likelihood(z, z_star, prm):
    """l_i of :func:`app.filter.likelihood_ref.pixel_log_likelihood` for one covered pixel (z* > 0)."""
    return _pixel_log_likelihood(z, math.exp(-prm[1] * z), z_star, prm)


@_njit()
def _pixel_log_likelihood(z, exp_lam_z, z_star, prm):
    """:func:`pixel_log_likelihood` given exp(-λ z), which :func:`batch` computes once per measured pixel.

    Same value, fewer transcendental calls: a pixel the background ratio makes neutral returns 0
    before any, and exp(-r²/2) is skipped where it is exactly 0.0 in float64 (r²/2 > 746).
    """
    z_max, w_u, w_e, w_n, l0 = prm[0], prm[2], prm[3], prm[4], prm[7]
    classification, ratio = prm[12] != 0.0, prm[13] != 0.0
    p_u, log_p_u = w_u / z_max, prm[15]
    if not (z > 0.0 and z <= z_max):       # 0, negative, > z_max, NaN, ±inf: invalid
        l_invalid = log_p_u - (l0 if classification else 0.0)
        return l_invalid - log_p_u if ratio else l_invalid
    if ratio and z < z_star - prm[10]:     # an occluder in front: says nothing about the bone
        return 0.0
    sigma = prm[5] * z_star * z_star + prm[6]
    r = (z - z_star) / sigma
    half_r2 = 0.5 * r * r
    p_n = _INV_SQRT_2PI / sigma * math.exp(-half_r2) if half_r2 < 746.0 else 0.0
    p_e = _occlusion_density(z, exp_lam_z, z_star, sigma, prm)
    if classification:
        l_obj = _safe_log(w_n * p_n)
        l_bg = _safe_log(p_u + w_e * p_e)
        l = l_obj if l_obj >= l_bg else l_bg - l0
    else:
        l = _safe_log(p_u + w_e * p_e + w_n * p_n)
    return l + prm[14] if ratio else l


@_njit()
def _score_and_clear(depth_meas, exp_lam_z, zbuf, box, prm):
    """α Σ l_i (or c_reg Σ l_i / max(N_px, 1)) over the covered pixels of ``box``; zeroes them.

    Without classification (:func:`pack_params` [16]) Σ log x_i = log Π x_i over the densities
    x_i = p_u + w_e p_e + w_n p_n >= p_u >= LOG_FLOOR (written out, one division 1 / σ), one log
    per block of pixels, the constants as count x constant (log p_u per invalid pixel, or log
    z_max per density with the background ratio); the product stays in [1e-150, 1e150] (a factor
    that would take it out is logged on its own), so the sum is the per-pixel logs' to rounding.
    """
    z_max, lam, w_u, w_e, w_n, k, sigma_base = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6]
    ratio, smooth, by_product = prm[13] != 0.0, prm[11] != 0.0, prm[16] != 0.0
    p_u = w_u / z_max
    total, product, n_density, n_invalid, count = 0.0, 1.0, 0, 0, 0
    for v in range(box[1], box[3] + 1):
        for u in range(box[0], box[2] + 1):
            z_star = zbuf[v, u]
            if z_star <= 0.0:
                continue
            zbuf[v, u] = 0.0
            count += 1
            z = float(depth_meas[v, u])
            if not by_product:
                total += _pixel_log_likelihood(z, exp_lam_z[v, u], z_star, prm)
                continue
            if not (z > 0.0 and z <= z_max):       # 0, negative, > z_max, NaN, ±inf: invalid
                n_invalid += 1
                continue
            if ratio and z < z_star - prm[10]:     # an occluder in front: neutral
                continue
            sigma = k * z_star * z_star + sigma_base
            inv_sigma = 1.0 / sigma
            r = (z - z_star) * inv_sigma
            half_r2 = 0.5 * r * r
            p_n = _INV_SQRT_2PI * inv_sigma * math.exp(-half_r2) if half_r2 < 746.0 else 0.0
            if smooth:
                p_e = _occlusion_density(z, exp_lam_z[v, u], z_star, sigma, prm)
            else:
                p_e = lam / (1.0 - math.exp(-lam * z_star)) * exp_lam_z[v, u] if z < z_star else 0.0
            x = p_u + w_e * p_e + w_n * p_n
            n_density += 1
            y = product * x
            if y > 1.0 / _PRODUCT_RANGE and y < _PRODUCT_RANGE:
                product = y
            else:
                total += math.log(product) + math.log(x)
                product = 1.0
    total += math.log(product) + (n_density * prm[14] if ratio else n_invalid * prm[15])
    return prm[8] * total / max(count, 1) if prm[8] > 0.0 else prm[9] * total


@_njit(parallel=True)
def batch(T_camera_bone, vertices, faces, cam, cull, depth_meas, prm, zbufs, out_ll, out_depth):
    """Render every pose; with ``out_depth`` of N images copy its depth there (0 = not covered),
    otherwise score it into ``out_ll[j]`` = log p(z | x_j) in the same pass (no depth image leaves
    the chunk's z-buffer). One parallel kernel for both keeps numba's compile time down."""
    n, chunks = T_camera_bone.shape[0], zbufs.shape[0]
    render = out_depth.shape[0] == n and n > 0
    h, w = depth_meas.shape
    exp_lam_z = np.empty((h, w))            # exp(-λ z) per measured pixel, once per call
    if not render and prm[11] == 0.0:
        for v in prange(h):
            for u in range(w):
                exp_lam_z[v, u] = math.exp(-prm[1] * float(depth_meas[v, u]))
    counter = np.zeros(1, np.int64)          # the next hypothesis to take (_take_next)
    for c in prange(chunks):
        p = np.empty((vertices.shape[0], 6))
        poly = np.empty((4, 3))
        box = np.empty(4, np.int64)
        zbuf = zbufs[c]
        while True:
            j = _take_next(counter)
            if j >= n:
                break
            _render_one(T_camera_bone[j], vertices, faces, cam, cull, p, poly, zbuf, box)
            if not render:
                out_ll[j] = _score_and_clear(depth_meas, exp_lam_z, zbuf, box, prm)
                continue
            out_depth[j, :, :] = 0.0
            for v in range(box[1], box[3] + 1):
                for u in range(box[0], box[2] + 1):
                    out_depth[j, v, u] = zbuf[v, u]
                    zbuf[v, u] = 0.0


@_njit()
def evidence_counts(T_camera_bone, vertices, faces, cam, cull, depth_meas, ev, zbuf, p, box):
    """(covered, inliers) of one pose (4, 4), as :func:`app.filter.observation.depth_evidence`
    counts them from the float32 rendering, over the pose's pixel box only; ``zbuf`` (h, w) all 0
    on entry and exit, ``p`` (V, 6) and ``box`` (4,) int64 scratch. ``ev`` = (z_max,
    occluder_margin, k, sigma_base, INLIER_SIGMAS).

    A covered pixel (z* > 0) with a valid measurement z (finite, 0 < z <= z_max) counts unless an
    occluder hides it (z < z* - margin, in float32 as numpy compares the float32 images); it is an
    inlier when |z - z*| < 3 σ(z*), σ(z*) = k z*² + σ_base (float64, likelihood_ref.inlier_mask).
    """
    poly = np.empty((4, 3))
    _render_one(T_camera_bone, vertices, faces, cam, cull, p, poly, zbuf, box)
    z_max, margin32, k, sigma_base, n_sigma = ev[0], np.float32(ev[1]), ev[2], ev[3], ev[4]
    covered, inliers = 0, 0
    for v in range(box[1], box[3] + 1):
        for u in range(box[0], box[2] + 1):
            z_star32 = np.float32(zbuf[v, u])
            zbuf[v, u] = 0.0
            z32 = depth_meas[v, u]
            z = float(z32)
            if not (z_star32 > 0.0 and z > 0.0 and z <= z_max) or z32 < z_star32 - margin32:
                continue
            covered += 1
            z_star = float(z_star32)
            if abs(z - z_star) < n_sigma * (k * z_star * z_star + sigma_base):
                inliers += 1
    return covered, inliers


def log_likelihood_batch(T_camera_bone, vertices, faces, cam, cull, depth_meas, prm, zbufs, out):
    """(N,) log p(z | x_j) into ``out`` (:func:`batch`)."""
    no_depth = np.zeros((0, 1, 1), dtype=np.float32)
    batch(T_camera_bone, vertices, faces, cam, cull, depth_meas, prm, zbufs, out, no_depth)


def render_batch(T_camera_bone, vertices, faces, cam, cull, zbufs, out):
    """Rendered linear depth of every pose into ``out`` (N, h, w) float32 (0 = not covered)."""
    h, w = out.shape[1:]
    batch(T_camera_bone, vertices, faces, cam, cull, np.zeros((h, w), np.float32), np.zeros(N_PARAMS),
          zbufs, np.empty(len(out)), out)
