"""Local refinement of the filter's estimate: robust Gauss-Newton point-to-plane on full-resolution depth.

Import as ``from app.filter.refine import Refiner``. DESIGN.md "Local refinement and the
estimate's uncertainty". The particle filter at 160x120 is robust but imprecise; this refines its
estimate T = ``T_camera_bone`` on the measured image at ``stride`` (1 = full, 2 = half sensor
resolution) inside the bone's projected bounding box. A small silhouette, fewer than
``fine_below`` = 1,150 cells at ``stride`` (the eight CT crests at 0.65 m: 672-1,031 cells at stride
2; at 0.42 m: 1,303-1,909), is refined at stride 1: four times the points where the bone is far
(BENCHMARKS.md §6d).

Model: the mesh sampled once, densely (``samples`` points x_j with normals n_j, bone frame; ~2.5 per
mm² on a CT crest, 0.6 mm apart), sorted into a grid of 2 mm cells for the nearest-sample search
(app/filter/refine_kernels.py, whose :func:`~app.filter.refine_kernels.gauss_newton` runs steps 3-6 in
one numba kernel; ``backend="numpy"`` keeps the cKDTree reference path, equal within float tolerance:
tests/test_refine_kernels.py, and on the eight CT crests' replays scripts/refine_calls.py, BENCHMARKS.md
"Filter rate and CPU"). Per iteration, at the current pose:

1. Expected visible surface (again after any step over ``rerender_step``; the association in
   step 3 is redone every iteration): the samples that face the camera, projected into a z-buffer on the
   crop's grid (min depth per pixel, empty pixels between covered ones filled by a 3x3 minimum:
   :func:`fill_holes`, which also grows the outline by a pixel with ``outline_ring``); its pixels are the
   bone's silhouette, z*_i its depth.
2. Measurements: the silhouette pixels with a valid depth z_i that is not an occluder
   (z_i >= z*_i - ``occluder_margin``, the likelihood's rule, app/filter/likelihood_ref.py),
   back-projected (y_i = z_i K⁻¹(u, v, 1)) and moved into the bone frame p_i = T⁻¹ y_i.
3. Association: the nearest model sample x_i, n_i within ``pair_radius`` = 5 mm (re-associated every
   iteration); a measurement with none as near (the background beside the bone's silhouette, tissue
   far from it) is not associated: left out of the fit, never confirmed, never behind. An annealed
   step of width w > 5 mm / 3 associates within ``PAIR_WIDTHS`` w = 3 w, its own cut-off in step 5:
   with the fixed 5 mm a wide first width had nothing to act on, and from crest_right_03's coarse
   start (or_coarse_start, 16 mm / 12 deg) no width converged (BENCHMARKS.md §6d). Tracking steps
   (width 0) and the final statistics keep 5 mm.
4. Point-to-plane residual r_i = n_iᵀ (p_i − x_i) (Chen & Medioni 1991; the small-angle
   linearisation of Low 2004, as in Stoiber's ICG depth modality): with the increment
   δ = (ω, v) applied to the measurements about the model's centre c (CT meshes keep the
   scanner's origin, far from the bone: rotating about it conditions H badly),
   p_i' ≈ p_i + ω × (p_i − c) + v, so r_i(δ) ≈ r_i + J_i δ with J_i = [((p_i − c) × n_i)ᵀ, n_iᵀ].
5. Robust weights: Tukey's biweight on r_i / s_k with s_k = max(c σ(z_i), annealed width), c = 3
   (σ includes the 1 mm model-mismatch floor; measured on crest_left_02 under 3 mm tissue patches,
   150 frames: c = 4.685 / 3 / 2 gave ADD median 1.72 / 1.55 / 1.46 mm, p95 8.2 / 1.7 / 1.5 mm):
   w_i = (1 − (r_i / s_k)²)² for |r_i| < s_k, else 0; pairs further apart than ``3 s_k`` are
   left out (not the same surface), and so are measurements more than max(k σ, width) in front
   of the model's depth: soft tissue over the buried part of a correctly placed bone is not
   evidence about it (DESIGN.md; measured: with the tissue kept, the fit from the true pose of a
   noisy synthetic frame drifted 0.76 mm out of the tissue; leaving out those more than 3 / 2 / 1.5 σ in front: 0.26 / 0.20 / 0.14 mm; without the tissue 0.04 mm).
   The tissue's border (``tissue_border``): where the tissue meets the bone its surface runs into
   the bone's at a shallow angle, so a band of tissue lies less than the cut-off in front of the
   buried flank; those measurements are kept by the rule above and pull the fit towards the camera
   on that side. A measurement whose neighbouring cell (8-neighbourhood on the crop grid,
   :func:`app.filter.refine_kernels.neighbours`) holds a buried measurement is left out too (the
   same width rule, so a wide first step, which buries nothing, keeps all). Measured at the truth of
   static_far crest_right_02 (BENCHMARKS.md §6i): the mean residual of the used measurements
   +0.74 mm, with the border +0.01 mm; refined from the truth (noise-free CT crests in tissue at
   0.65 m, tests/test_refine.py) 0.32-0.34 mm off without it, 0.05-0.07 with it.
6. Gauss-Newton: (Σ w_i J_iᵀJ_i / σ_i²) δ = −Σ w_i J_iᵀ r_i / σ_i², then T ← T exp(δ)⁻¹.
7. At the final pose, the share ``behind`` of the measurements whose surface lies more than
   ``behind_sigmas`` = 1 σ inside the model (r_i < −σ_i, normals outward). Tissue and occluders only
   ever lie in front of the bone; a pose pushed part-way onto residual tissue passes through the
   seen surface elsewhere (measured on crest_left_02, or_deep_tissue, a 3 mm patch: the fit 1.5 mm
   off has 2.8-3.9 % behind, the truth 0.3-0.7 %; static_clear 0.5-0.7 % at 0.42 m, 0.9-1.7 % at
   0.65 m where the sensor's noise is a larger part of σ). Beside it ``behind_allowed``, the share
   the image's own noise explains (:func:`behind_bound`), with σ̂_n the robust scale of the fit's
   residuals behind the model and the count's variance multiplied by their spatial correlation
   factor f = n / n_eff (app/tracking/fit_test.py): the status compares the two (status.py).
8. When the last step was below the stopping rule (``stop_translation`` / ``stop_rotation``) and the
   annealed width no longer mattered, the statistics of step 7 and H are those of that last
   association instead of a new render and association at the final pose (a step under 0.1 mm /
   0.03 deg): one z-buffer and one association per frame fewer while tracking.

Outputs (:class:`RefineResult`): the refined ``T_camera_bone``; H = Σ w_i J_iᵀJ_i / σ_i² (6x6, in
the bone frame about ``Refiner.center``, order ω then v), the information the image carries about the
pose were its pixels independent (the status's ``covariance_inflation`` covers their correlation and
the model's error: measured against the template's error on the independent and the stereo sensor
models, BENCHMARKS.md "Status"; dividing by the measured correlation factor f instead over-covered
a near stereo view tenfold); the fitness
(the share of the expected visible surface that the image confirms: silhouette pixels, occluders
left out, whose measurement lies within ``confirm_sigmas`` σ(z) of the model) and the residual
statistics, and the sharper share within ``sharp_sigmas`` = 1 σ that decides between two fits
(measured on crest_right_02, static_clear: the truth and a fit 3.7-5.3 mm off confirmed 0.83 vs
0.82-0.83 within 3 σ, 0.62 vs 0.51-0.56 within 1 σ). σ(z) = k z² + σ_base, the likelihood's sensor model.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from app.filter import refine_kernels as kernels
from app.filter.behind_noise import behind_moments, noise_bound
from app.tracking import fit_kernels, fit_test
from app.geometry import se3
from app.geometry.camera import PinholeCamera

TUKEY_C = 3.0   # Tukey's constant in σ(z): 4.685 is the 95 %-efficiency value; 3 measured less biased by tissue
RENDER_LEVER = 0.05   # m, radius at which a rotation step is compared with rerender_step
FINE_BELOW = 1150     # silhouette cells at ``stride`` under which a frame is refined at stride 1 (module docstring)
PAIR_WIDTHS = 3.0     # a step of width w associates pairs up to PAIR_WIDTHS w apart (its Tukey cut-off, step 5)
NO_NEIGHBOURS = np.zeros((0, 8), np.int64)   # normal_equations without the tissue border
GRID_CELL = 0.002     # m, cell of the samples' grid for the nearest-sample search: 2 mm took 0.6-0.7x the CPU of 1 mm (0.7 mm: 1.7x) on a CT crest at 0.42 and 0.65 m


@dataclass
class RefineParams:
    """Settings (metres). stride : 1 full / 2 half sensor resolution; tukey_c : Tukey's constant in
    units of σ(z); iterations : GN steps;
    samples : model points; front_sigmas : measurements more than this many σ (or the
    annealed width) in front of the model are left out of the fit (buried bone); start_width : the first iteration's Tukey width (annealed by half per
    iteration down to c σ(z)); confirm_sigmas : k of the fitness; k, sigma_base : σ(z) = k z² + σ_base;
    occluder_margin : a measurement this far in front of the model is an occluder; min_points :
    fewer associated points and the refinement declines (returns the input pose, ``converged`` False);
    stop_translation (m) / stop_rotation (rad) : an increment smaller than both ends the iterations;
    rerender_step (m) : the silhouette and the measurements are taken again only after a step that
    moved the model more than this (translation, or rotation x 5 cm); re-association is every step;
    outline_ring : the z-buffer's hole fill also grows the silhouette by a pixel (:func:`fill_holes`);
    tissue_border : a measurement next to a buried one (its 8 neighbouring cells) is left out of the
    fit (step 5); noise_window_px : the detrending window of the noise's scale and correlation (px,
    step 7; app/tracking/fit_test.py).
    """

    stride: int = 2
    tukey_c: float = TUKEY_C
    iterations: int = 5
    samples: int = 30_000
    start_width: float = 0.010
    confirm_sigmas: float = 3.0
    sharp_sigmas: float = 1.0
    behind_sigmas: float = 1.0
    front_sigmas: float = 1.5
    k: float = 0.0011
    sigma_base: float = 0.001
    occluder_margin: float = 0.02
    min_points: int = 50
    stop_translation: float = 1e-4
    rerender_step: float = 5e-4
    stop_rotation: float = 5e-4
    fine_below: int = FINE_BELOW
    pair_radius: float = 0.005
    behind_z: float = 3.0
    backend: str = "numba"
    outline_ring: bool = False
    tissue_border: bool = True
    noise_window_px: int = fit_test.WINDOW_PX


@dataclass
class RefineResult:
    """T_camera_bone (4, 4); H (6, 6) information (bone frame, ω then v); fitness in [0, 1] (NaN when
    the silhouette has no usable pixel); expected : silhouette pixels with a usable measurement;
    confirmed : of those, within confirm_sigmas σ; used : points in the last GN step;
    rms : weighted RMS point-to-plane residual (m); converged : the GN steps ran (enough points);
    sharp : the share within ``sharp_sigmas`` σ (separates two nearly equal fits better);
    behind : the share whose measured surface lies more than ``behind_sigmas`` σ inside the model
    (signed point-to-plane residual n_iᵀ(p_i − x_i) < −behind_sigmas σ_i): light does not pass
    through bone, so a right pose leaves only the noise's tail there (module docstring, step 7);
    behind_allowed : the noise bound on it; noise : the image's noise estimate (m); stride : the grid
    step it was refined at (0 when unknown); behind_mean / behind_var : the mean and variance of the
    count the noise alone puts behind (:func:`app.filter.behind_noise.behind_moments`, the variance
    multiplied by ``correlation``; NaN: unknown); correlation : f = n / n_eff of the residuals
    (app/tracking/fit_test.py)."""

    T_camera_bone: np.ndarray
    H: np.ndarray
    fitness: float
    expected: int
    confirmed: int
    used: int
    rms: float
    converged: bool
    sharp: float = float("nan")
    behind: float = float("nan")
    behind_allowed: float = float("nan")
    noise: float = float("nan")
    stride: int = 0
    behind_mean: float = float("nan")
    behind_var: float = float("nan")
    correlation: float = 1.0


def fill_holes(zbuf: np.ndarray, ring: bool = False) -> np.ndarray:
    """The z-buffer's empty cells filled with the minimum of their 3x3 neighbourhood (step 1).

    Without ``ring`` (``RefineParams.outline_ring``, off by default): only a cell between two covered
    ones (left and right, above and below, or across either diagonal), the one-cell gaps between the
    samples; the outline is not grown. With it: every empty cell next to a covered one, so the
    silhouette is grown by a full-resolution pixel all round.

    Measured on the eight CT crests (BENCHMARKS.md §6h, §6i). The ring's measurements beside the
    silhouette are tissue where the tissue meets the bone, within ``pair_radius`` of the buried
    flank: refined from the truth, static_far crest_right_03 seed 1's mean fit is 0.53 mm / 0.81 deg
    off with the ring, 0.06 / 0.04 without. On crest_right_02 the ring seemed to carry the edge's
    information (without it static_far's fits were 0.40-0.51 mm / 0.66-0.89 deg off, with it
    0.20-0.30 / 0.22-0.39), but the sensor leaves no valid pixel at a depth edge: the ring only
    offset the pull of the tissue's border (step 5), and with that border left out the fits are
    0.08-0.12 mm / 0.10-0.22 deg off without the ring, worse with it (0.23-0.35 mm)."""
    covered = np.isfinite(zbuf)
    filled = ndimage.minimum_filter(zbuf, size=3, mode="constant", cval=np.inf)
    if ring:
        return np.where(covered, zbuf, filled)
    pad = np.pad(covered, 1)
    h, w = zbuf.shape

    def side(dr: int, dc: int) -> np.ndarray:
        return pad[1 + dr:1 + dr + h, 1 + dc:1 + dc + w]
    between = ((side(0, -1) & side(0, 1)) | (side(-1, 0) & side(1, 0))
               | (side(-1, -1) & side(1, 1)) | (side(-1, 1) & side(1, -1)))
    between[[0, -1], :] = False
    between[:, [0, -1]] = False
    return np.where(~covered & between, filled, zbuf)


def exp_se3(delta: np.ndarray) -> np.ndarray:
    """exp of δ = (ω, v) as a 4x4 (Rodrigues for R; the translation taken as v, first order)."""
    T = se3.from_rotvec_trans(np.asarray(delta[:3], float), np.asarray(delta[3:], float))
    return T


class Refiner:
    """Refines a pose of one mesh against full-resolution depth images of one camera (module docstring).

    Parameters
    ----------
    vertices, faces : the bone mesh (bone frame, metres)
    camera : the depth camera at the resolution of the images passed to :meth:`refine`
    params : RefineParams
    seed : seed of the surface sampling (deterministic)
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, camera: PinholeCamera,
                 params: RefineParams | None = None, seed: int = 0):
        import trimesh

        self.params = params or RefineParams()
        if self.params.backend not in ("numba", "numpy"):
            raise ValueError(f"refine backend {self.params.backend!r}: numba | numpy")
        self.camera = camera
        mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
        points, face_idx = trimesh.sample.sample_surface(mesh, self.params.samples, seed=seed)
        self.points = np.asarray(points, float)
        self.normals = np.asarray(mesh.face_normals[face_idx], float)
        self.tree = cKDTree(self.points) if self.params.backend == "numpy" else None
        self.center = self.points.mean(axis=0)
        self.grid = kernels.build_grid(self.points, self.normals, GRID_CELL) if self.params.backend == "numba" else None

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """σ(z) = k z² + σ_base (DESIGN.md's sensor model), metres."""
        return self.params.k * z * z + self.params.sigma_base

    def model_depth(self, T_camera_bone: np.ndarray, stride: int | None = None) -> tuple[np.ndarray, tuple[int, int, int, int]]:
        """z-buffer of the camera-facing samples, rendered at the full resolution and taken every
        ``stride`` pixels (default the params'): (h, w) depth (inf = not covered) and the crop
        (x0, y0, x1, y1) in full-resolution pixels. Rendering on the coarse grid instead (each cell the
        nearest of the samples over s x s pixels) widens the silhouette by half a cell onto the
        background and biases the fit: crest_right_03 static_clear, 14 frames refined from the truth,
        rotation / ADD median 0.51 deg / 0.32 mm against 0.14 deg / 0.12 mm (BENCHMARKS.md §6d)."""
        s = stride or self.params.stride
        zbuf, x0, y0 = self._render(T_camera_bone)
        if zbuf.size == 0:
            return zbuf, (0, 0, 0, 0)
        zbuf = np.ascontiguousarray(zbuf[::s, ::s])
        return zbuf, (x0, y0, x0 + zbuf.shape[1] * s, y0 + zbuf.shape[0] * s)

    def _render(self, T_camera_bone: np.ndarray) -> tuple[np.ndarray, int, int]:
        """The full-resolution z-buffer of the crop around the silhouette and its corner (x0, y0)."""
        cam = self.camera
        R, t = T_camera_bone[:3, :3], T_camera_bone[:3, 3]
        if self.grid is not None:
            return kernels.zbuffer(self.points, self.normals, np.ascontiguousarray(R), np.ascontiguousarray(t),
                                   cam.fx, cam.fy, cam.cx, cam.cy, 1, cam.width, cam.height,
                                   self.params.outline_ring)
        p_cam = self.points @ R.T + t
        n_cam = self.normals @ R.T
        facing = (np.einsum("ij,ij->i", n_cam, p_cam) < 0) & (p_cam[:, 2] > 0)
        uv, z = cam.project(p_cam[facing])
        col, row = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        if not inside.any():
            return np.full((0, 0), np.inf), 0, 0
        col, row, z = col[inside], row[inside], z[inside]
        c0, c1 = max(col.min() - 1, 0), min(col.max() + 2, cam.width)
        r0, r1 = max(row.min() - 1, 0), min(row.max() + 2, cam.height)
        zbuf = np.full((r1 - r0, c1 - c0), np.inf)
        order = np.argsort(-z)                     # far to near: the nearest sample is written last
        zbuf[row[order] - r0, col[order] - c0] = z[order]
        return fill_holes(zbuf, self.params.outline_ring), int(c0), int(r0)

    def measurements(self, depth: np.ndarray, T_camera_bone: np.ndarray,
                     stride: int | None = None, rendered=None) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points y_i (M, 3) of the silhouette's usable pixels and their z*_i (M,);
        ``rendered``: :meth:`model_depth`'s result at this pose and stride when already computed."""
        s, cam = stride or self.params.stride, self.camera
        zbuf, (x0, y0, _, _) = rendered if rendered is not None else self.model_depth(T_camera_bone, s)
        if zbuf.size == 0:
            return np.zeros((0, 3)), np.zeros(0)
        if self.grid is not None:
            return kernels.measurements(depth, zbuf, x0, y0, s, cam.fx, cam.fy, cam.cx, cam.cy, self.params.occluder_margin)
        z, zbuf, usable = self._usable_cells(depth, zbuf, x0, y0, s)
        rows, cols = np.nonzero(usable)
        zi = z[rows, cols]
        u, v = x0 + cols * s, y0 + rows * s
        y = np.column_stack([(u - cam.cx) / cam.fx * zi, (v - cam.cy) / cam.fy * zi, zi])
        return y, zbuf[rows, cols]

    def _usable_cells(self, depth, zbuf, x0, y0, s):
        """The numpy reference of the kernels' ``_usable``: (z, z*, usable) on the crop grid of step ``s``
        at (x0, y0), cut to the image (step 2)."""
        z = np.asarray(depth[y0::s, x0::s], float)[:zbuf.shape[0], :zbuf.shape[1]]
        zbuf = zbuf[:z.shape[0], :z.shape[1]]
        with np.errstate(invalid="ignore"):
            usable = np.isfinite(zbuf) & np.isfinite(z) & (z > 0) & (z >= zbuf - self.params.occluder_margin)
        return z, zbuf, usable

    def neighbours(self, depth: np.ndarray, rendered, stride: int) -> np.ndarray:
        """(M, 8) indices of each measurement's neighbours on the crop grid (-1: none), in the order
        of :meth:`measurements` at the same ``rendered`` z-buffer; (0, 8) without ``tissue_border``."""
        zbuf, (x0, y0, _, _) = rendered
        if not self.params.tissue_border or zbuf.size == 0:
            return NO_NEIGHBOURS
        if self.grid is not None:
            return kernels.neighbours(depth, zbuf, x0, y0, stride, self.params.occluder_margin)
        usable = self._usable_cells(depth, zbuf, x0, y0, stride)[2]
        index = np.where(usable, np.cumsum(usable).reshape(usable.shape) - 1, -1)
        padded = np.pad(index, 1, constant_values=-1)
        h, w = index.shape
        shifted = [padded[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
        return np.stack([s[usable] for s in shifted], axis=1).astype(np.int64).reshape(-1, 8)

    def _measure(self, depth, T_camera_bone, stride, rendered=None):
        """(y, z*, neighbours): :meth:`measurements` and :meth:`neighbours` of one z-buffer."""
        if rendered is None:
            rendered = self.model_depth(T_camera_bone, stride)
        y, z_model = self.measurements(depth, T_camera_bone, stride, rendered)
        return y, z_model, self.neighbours(depth, rendered, stride)

    def choose_stride(self, T_camera_bone: np.ndarray):
        """(stride, rendered): the grid step of this frame, ``params.stride``, or 1 when the bone's
        silhouette at that step has fewer than ``fine_below`` cells (a far or small view: four times
        the points; module docstring); ``rendered`` the z-buffer at that stride when it was computed."""
        s = self.params.stride
        if s == 1 or self.params.fine_below <= 0:
            return s, None
        rendered = self.model_depth(T_camera_bone, s)
        if np.count_nonzero(np.isfinite(rendered[0])) < self.params.fine_below:
            return 1, None
        return s, rendered

    def _associate(self, y_cam: np.ndarray, T_camera_bone: np.ndarray, radius: float | None = None):
        """Bone-frame points p_i, nearest samples' x_i, n_i and point distances d_i (none within
        ``radius``, default ``pair_radius``: not associated)."""
        radius = self.params.pair_radius if radius is None else radius
        p = se3.transform_points(se3.inverse(T_camera_bone), y_cam)
        if self.grid is None:
            d, j = self.tree.query(p, distance_upper_bound=radius)
            far = j >= len(self.points)            # none within pair_radius: not associated (NaN residual)
            j[far] = 0
            x, n = self.points[j], self.normals[j]
            x[far], n[far] = np.nan, np.nan
            return p, x, n, d
        g = self.grid
        j, d = kernels.nearest(np.ascontiguousarray(p), g.points, g.start, g.empty, g.origin, g.cell, g.dims, radius)
        x, n = kernels.gather(j, g.points, g.normals)
        return p, x, n, d

    def _gn_step(self, p, x, n, d, sigma, width, in_front, nbrs=NO_NEIGHBOURS):
        """One weighted GN system: returns (δ, H, used, weighted rms). ``in_front`` (M,) m: how far
        each measurement lies in front of the model's depth z* (z* − z); ``nbrs``: :meth:`neighbours`."""
        prm = self.params
        if self.grid is not None:
            H, g, used, num, den = kernels.normal_equations(p, x, n, d, sigma, in_front, self.center, float(width),
                                                            prm.tukey_c, prm.front_sigmas, nbrs)
        else:
            H, g, used, num, den = self._normal_equations(p, x, n, d, sigma, width, in_front, nbrs)
        if used < prm.min_points:
            return None, H, used, float("nan")
        delta = -np.linalg.solve(H + 1e-12 * np.eye(6), g)
        return delta, H, used, float(np.sqrt(num / max(den, 1e-30)))

    def _normal_equations(self, p, x, n, d, sigma, width, in_front, nbrs=NO_NEIGHBOURS):
        """The numpy reference of :func:`app.filter.refine_kernels.normal_equations` (steps 4-6)."""
        r = np.einsum("ij,ij->i", n, p - x)
        s = np.maximum(self.params.tukey_c * sigma, width)
        buried = in_front > np.maximum(self.params.front_sigmas * sigma, width)
        keep = (np.abs(r) < s) & (d < 3.0 * s) & ~buried
        if len(nbrs) == len(p) and len(p):
            keep &= ~np.any((nbrs >= 0) & buried[np.maximum(nbrs, 0)], axis=1)
        u = r[keep] / s[keep]
        w = (1.0 - u * u) ** 2 / sigma[keep] ** 2
        J = np.column_stack([np.cross(p[keep] - self.center, n[keep]), n[keep]])
        H = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r[keep]
        wsig = w * sigma[keep] ** 2
        return H, g, int(keep.sum()), float(np.sum(wsig * r[keep] ** 2)), float(np.sum(wsig))

    def refine(self, depth: np.ndarray, T_camera_bone: np.ndarray, start_width: float | None = None) -> RefineResult:
        """Refine ``T_camera_bone`` (4, 4) on ``depth`` ((H, W) metres at the camera's resolution).
        ``start_width`` (m, default ``params.start_width``): the first Tukey width; 0 from a pose
        already close (the track's last one), where a wide first step only lets the tissue pull.
        When the last step was below the stopping rule and the Tukey width had no effect any more
        (<= front_sigmas σ), the statistics are those of that last association (step 8): a step of
        < 0.1 mm / 0.03 deg does not change them, and a re-render and re-association cost as much as
        an iteration."""
        prm = self.params
        start_width = prm.start_width if start_width is None else start_width
        T = np.array(T_camera_bone, dtype=float)
        H, used, rms, ok = np.zeros((6, 6)), 0, float("nan"), False
        stride, rendered = self.choose_stride(T)
        if self.grid is not None:
            return self._refine_kernel(depth, T, start_width, stride, rendered)
        y, last = None, None
        for it in range(prm.iterations):
            if y is None:                          # re-render after a step that moved the model visibly
                y, z_model, nbrs = self._measure(depth, T, stride, rendered)
                rendered = None
                sigma = self.sigma(y[:, 2])
            if len(y) < prm.min_points:
                break
            width = start_width * 0.5 ** it
            p, x, n, d = self._associate(y, T, max(prm.pair_radius, PAIR_WIDTHS * width))
            delta, H, used, rms = self._gn_step(p, x, n, d, sigma, width, z_model - y[:, 2], nbrs)
            if delta is None:
                break
            ok = True
            T = T @ se3.inverse(self._increment(delta))
            step_r, step_t = np.linalg.norm(delta[:3]), np.linalg.norm(delta[3:])
            if step_r < prm.stop_rotation and step_t < prm.stop_translation:
                if width <= prm.front_sigmas * sigma.min():
                    last = (y, p, x, n, d, sigma)
                break
            if step_r * RENDER_LEVER > prm.rerender_step or step_t > prm.rerender_step:
                y = None
        if last is not None:
            return self._result(depth, T, H, used, rms, ok, *last, stride=stride)
        return self._finish(depth, T if ok else np.array(T_camera_bone, float), H, used, rms, ok, stride)

    def _refine_kernel(self, depth, T, start_width, stride, rendered) -> RefineResult:
        """:meth:`refine`'s iterations in :func:`app.filter.refine_kernels.gauss_newton` (the numba
        backend): the kernel runs until it must measure again, declines, stops or has no iteration left."""
        prm, g = self.params, self.grid
        T0 = T.copy()
        H, used, rms, ok, it, last = np.zeros((6, 6)), 0, float("nan"), False, 0, None
        while it < prm.iterations:
            y, z_model, nbrs = self._measure(depth, T, stride, rendered)
            rendered = None
            if len(y) < prm.min_points:
                break
            sigma = self.sigma(y[:, 2])
            T_new, H, used, rms, state, it, p, x, n, d = kernels.gauss_newton(
                y, sigma, z_model - y[:, 2], nbrs, T, it, prm.iterations, float(start_width), self.center,
                g.points, g.normals, g.start, g.empty, g.origin, g.cell, g.dims, prm.pair_radius, PAIR_WIDTHS,
                prm.tukey_c, prm.front_sigmas, prm.min_points, prm.stop_rotation, prm.stop_translation,
                prm.rerender_step, RENDER_LEVER)
            if state == kernels.GN_DECLINED:
                break
            ok, T = True, T_new
            if state == kernels.GN_STOPPED:
                if start_width * 0.5 ** it <= prm.front_sigmas * sigma.min():
                    last = (y, p, x, n, d, sigma)
                break
            if state == kernels.GN_DONE:
                break
        if last is not None:
            return self._result(depth, T, H, used, rms, ok, *last, stride=stride)
        return self._finish(depth, T if ok else T0, H, used, rms, ok, stride)

    def score(self, depth: np.ndarray, T_camera_bone: np.ndarray) -> RefineResult:
        """The statistics of step 7 at ``T_camera_bone`` as it is (no Gauss-Newton step; H is zero):
        fitness, sharp and behind shares of this pose on this image."""
        T = np.array(T_camera_bone, dtype=float)
        stride, rendered = self.choose_stride(T)
        return self._finish(depth, T, np.zeros((6, 6)), 0, float("nan"), False, stride, rendered)

    def _increment(self, delta: np.ndarray) -> np.ndarray:
        """exp(δ) about the model's centre c (the Jacobian's origin): p ↦ c + R (p − c) + v."""
        M = exp_se3(delta)
        M[:3, 3] += self.center - M[:3, :3] @ self.center
        return M

    def _finish(self, depth, T, H, used, rms, ok, stride, rendered=None) -> RefineResult:
        """Fitness, counts and the information matrix at the final pose (``rendered``: its z-buffer at
        ``stride`` when already drawn)."""
        y, z_model, nbrs = self._measure(depth, T, stride, rendered)
        if len(y) == 0:
            return RefineResult(T, H, float("nan"), 0, 0, used, rms, ok, stride=stride)
        p, x, n, d = self._associate(y, T)
        sigma = self.sigma(y[:, 2])
        if ok:
            _, H, used, rms = self._gn_step(p, x, n, d, sigma, 0.0, z_model - y[:, 2], nbrs)
        return self._result(depth, T, H, used, rms, ok, y, p, x, n, d, sigma, stride)

    def _result(self, depth, T, H, used, rms, ok, y, p, x, n, d, sigma, stride) -> RefineResult:
        """Fitness, sharp and behind shares of one association (steps 7-8); unassociated points
        (none within ``pair_radius``: d = inf, NaN residual) count as neither confirmed nor behind."""
        prm = self.params
        if self.grid is not None:
            cam = self.camera
            confirmed, sharp, behind, noise, factor, mean, var = kernels.statistics(
                y, p, x, n, d, sigma, T, prm.confirm_sigmas, prm.sharp_sigmas, prm.behind_sigmas, int(stride),
                cam.fx, cam.fy, cam.cx, cam.cy, fit_test.window_cells(stride, prm.noise_window_px))
            var *= factor
            allowed = noise_bound(mean, var, len(p), prm.behind_z)
            return RefineResult(T, H, confirmed / len(p), len(p), confirmed, used, rms, ok, sharp, behind, allowed,
                                noise, stride, mean, var, factor)
        confirmed = int(np.sum(d < prm.confirm_sigmas * sigma))
        sharp = float(np.mean(d < prm.sharp_sigmas * sigma))
        r = np.einsum("ij,ij->i", n, p - x)
        with np.errstate(invalid="ignore"):
            behind = float(np.mean(r < -prm.behind_sigmas * sigma))
        camera_bone = se3.inverse(T)[:3, 3]
        noise, factor = self._residual_noise(y, p, n, r, camera_bone, stride)
        mean, var = behind_moments(p, n, sigma * prm.behind_sigmas, noise, camera_bone)
        var *= factor
        allowed = noise_bound(mean, var, len(p), prm.behind_z)
        return RefineResult(T, H, confirmed / len(p), len(p), confirmed, used, rms, ok, sharp, behind, allowed, noise,
                            stride, mean, var, factor)

    def _residual_noise(self, y, p, n, r, camera_bone, stride) -> tuple[float, float]:
        """(σ̂_n, f): the depth noise's scale from the fitted surface's rough residual field and its
        correlation factor on the refinement's grid (app/tracking/fit_test.py; step 7)."""
        cam = self.camera
        window = fit_test.window_cells(stride, self.params.noise_window_px)
        if self.grid is not None:
            return fit_kernels.residual_noise(y, p, n, r, camera_bone, int(stride), cam.fx, cam.fy, cam.cx, cam.cy,
                                              self.sigma(y[:, 2]), window)
        ray = p - camera_bone
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.einsum("ij,ij->i", n, ray) / np.linalg.norm(ray, axis=1)
        u = fit_test.depth_residuals(r, cos)
        with np.errstate(invalid="ignore", divide="ignore"):
            cols = np.rint(y[:, 0] / y[:, 2] * cam.fx + cam.cx) // max(stride, 1)
            rows = np.rint(y[:, 1] / y[:, 2] * cam.fy + cam.cy) // max(stride, 1)
        cells = np.column_stack([np.nan_to_num(cols), np.nan_to_num(rows)]).astype(np.int64)
        return fit_test.noise_and_factor(fit_test.noise_field(cells, u, self.sigma(y[:, 2]), window), window)


def template_std(H: np.ndarray, points_bone: np.ndarray, inflation: float = 1.0) -> float:
    """Largest predicted standard deviation (m) of the template's points ``points_bone`` (K, 3).

    Σ = inflation · H⁻¹ (the refinement's pose covariance, inflated for correlated pixels;
    DESIGN.md); the points relative to the origin of H's rotation (``Refiner.center``). A point t moves by ω × t + v under δ = (ω, v), i.e. A_t δ with A_t = [−[t]ₓ, I];
    its covariance is A_t Σ A_tᵀ and the result is the largest sqrt eigenvalue over the points.
    Infinite when H is singular (a direction the image does not constrain).
    """
    try:
        sigma = inflation * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return float("inf")
    if not np.all(np.isfinite(sigma)) or np.linalg.cond(H) > 1e14:
        return float("inf")
    t = np.asarray(points_bone, float).reshape(-1, 3)
    A = np.zeros((len(t), 3, 6))
    A[:, 0, 1], A[:, 0, 2], A[:, 1, 0] = t[:, 2], -t[:, 1], -t[:, 2]     # −[t]ₓ
    A[:, 1, 2], A[:, 2, 0], A[:, 2, 1] = t[:, 0], t[:, 1], -t[:, 0]
    A[:, :, 3:] = np.eye(3)
    cov = A @ sigma @ np.swapaxes(A, 1, 2)
    worst = float(np.linalg.eigvalsh(cov).max()) if len(t) else 0.0
    return float(np.sqrt(max(worst, 0.0)))
