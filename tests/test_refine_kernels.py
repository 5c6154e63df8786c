"""The refinement's numba kernels (app/filter/refine_kernels.py) against the numpy reference path of
app/filter/refine.py (``RefineParams(backend="numpy")``) and scipy's k-d tree, on random poses."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from app.filter import refine_kernels as kernels
from app.filter.refine import NO_NEIGHBOURS, Refiner, RefineParams
from app.geometry import se3
from app.sim.simulator import D415_640x480
from tests.scenes import synthetic_crest


@pytest.fixture(scope="module")
def crest():
    return synthetic_crest()


@pytest.fixture(scope="module")
def refiners(crest):
    vertices, faces = crest
    return {b: Refiner(vertices, faces, D415_640x480, RefineParams(backend=b, samples=20_000)) for b in ("numpy", "numba")}


def _pose(rng, distance=0.42):
    """The crest facing the camera at ``distance``, turned by up to ~11 deg and shifted a few mm."""
    return se3.from_rotvec_trans(np.array([np.pi, 0.0, 0.0]) + rng.normal(0, 0.1, 3),
                                 np.array([0.0, 0.0, distance]) + rng.normal(0, 0.005, 3))


def _depth(refiner, T, rng, noise=0.0008):
    """A full-resolution depth image of the model at T (its stride-1 z-buffer) with noise, zeros elsewhere
    and 1 % invalid pixels."""
    zbuf, (x0, y0, _, _) = refiner.model_depth(T, 1)
    depth = np.zeros((D415_640x480.height, D415_640x480.width), np.float32)
    h = min(zbuf.shape[0], depth.shape[0] - y0)
    w = min(zbuf.shape[1], depth.shape[1] - x0)
    z = np.where(np.isfinite(zbuf[:h, :w]), zbuf[:h, :w] + rng.normal(0, noise, (h, w)), 0.0)
    depth[y0:y0 + h, x0:x0 + w] = np.where(rng.random((h, w)) < 0.01, 0.0, z)
    return depth


@pytest.mark.parametrize("radius, cell", [(0.005, 0.001), (0.005, 0.002), (0.03, 0.002)])
def test_nearest_matches_the_kd_tree_within_the_radius(rng, radius, cell):
    """The grid search (cells farther than the best so far are not opened) finds the k-d tree's nearest
    sample, the same index and distance, and none where the k-d tree finds none within the radius."""
    points = rng.normal(size=(5000, 3)) * [0.03, 0.02, 0.002]
    grid = kernels.build_grid(points, np.tile([0.0, 0.0, 1.0], (5000, 1)), cell)
    query = np.concatenate([points[:300] + rng.normal(0, 0.001, (300, 3)),            # near the samples
                            points[300:600] + rng.normal(0, radius / 2, (300, 3)),    # about the radius away
                            rng.uniform(-0.12, 0.12, (300, 3))])                      # inside and outside the grid
    j, d = kernels.nearest(query, grid.points, grid.start, grid.empty, grid.origin, grid.cell, grid.dims, radius)
    d_ref, j_ref = cKDTree(points).query(query, distance_upper_bound=radius)
    found = np.isfinite(d_ref)
    assert 350 < found.sum() < 900                 # both kinds of query occur
    np.testing.assert_array_equal(j >= 0, found)
    np.testing.assert_allclose(d[found], d_ref[found], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(grid.index[j[found]], j_ref[found])


@pytest.mark.parametrize("stride", [1, 2])
def test_zbuffer_and_measurements_match_numpy(refiners, stride, rng):
    for _ in range(5):
        T = _pose(rng)
        depth = _depth(refiners["numpy"], T, rng)
        T_off = T @ se3.from_rotvec_trans(rng.normal(0, 0.02, 3), rng.normal(0, 0.002, 3))
        zb_np, crop_np = refiners["numpy"].model_depth(T_off, stride)
        zb_nb, crop_nb = refiners["numba"].model_depth(T_off, stride)
        assert crop_np == crop_nb
        np.testing.assert_array_equal(np.isfinite(zb_np), np.isfinite(zb_nb))
        np.testing.assert_allclose(zb_nb[np.isfinite(zb_nb)], zb_np[np.isfinite(zb_np)], rtol=0, atol=1e-12)
        y_np, z_np = refiners["numpy"].measurements(depth, T_off, stride)
        y_nb, z_nb = refiners["numba"].measurements(depth, T_off, stride)
        assert len(y_np) > 500
        np.testing.assert_allclose(y_nb, y_np, rtol=0, atol=1e-12)
        np.testing.assert_allclose(z_nb, z_np, rtol=0, atol=1e-12)


def test_normal_equations_match_numpy(refiners, rng):
    ref_np, ref_nb = refiners["numpy"], refiners["numba"]
    T = _pose(rng)
    depth = _depth(ref_np, T, rng)
    y, z_model = ref_np.measurements(depth, T)
    y[::7, 2] -= 0.004                            # some measurements in front of the model (tissue)
    p, x, n, d = ref_np._associate(y, T)
    sigma = ref_np.sigma(y[:, 2])
    nbrs = kernels.neighbours(depth, *_zbuf_and_corner(ref_nb, T), 2, ref_nb.params.occluder_margin)
    for width in (0.0, 0.002, 0.01):
        for border in (NO_NEIGHBOURS, nbrs):
            H, g, used, num, den = kernels.normal_equations(p, x, n, d, sigma, z_model - y[:, 2], ref_nb.center, width,
                                                            ref_nb.params.tukey_c, ref_nb.params.front_sigmas, border)
            H_ref, g_ref, used_ref, num_ref, den_ref = ref_np._normal_equations(p, x, n, d, sigma, width, z_model - y[:, 2],
                                                                                border)
            assert used == used_ref > 100
            np.testing.assert_allclose(H, H_ref, rtol=1e-10, atol=1e-10 * np.abs(H_ref).max())
            np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-10 * np.abs(g_ref).max())
            assert num == pytest.approx(num_ref, rel=1e-10) and den == pytest.approx(den_ref, rel=1e-10)
        without = kernels.normal_equations(p, x, n, d, sigma, z_model - y[:, 2], ref_nb.center, width,
                                           ref_nb.params.tukey_c, ref_nb.params.front_sigmas, NO_NEIGHBOURS)[2]
        if width < 0.004:            # the 4 mm are buried: their neighbours leave the fit
            assert used < 0.8 * without
        else:                        # a wider step buries nothing: the border is empty
            assert used == without


def _zbuf_and_corner(refiner, T):
    zbuf, (x0, y0, _, _) = refiner.model_depth(T, 2)
    return zbuf, x0, y0


def test_neighbours_match_numpy_and_the_grid(refiners, rng):
    """Each measurement's 8 neighbours (refine_kernels.neighbours, the tissue border of step 5): numba =
    numpy, in :meth:`Refiner.measurements`' order, and a neighbour of a neighbour's cell is the cell
    itself (the relation is symmetric); the image's invalid pixels have none."""
    T = _pose(rng)
    depth = _depth(refiners["numpy"], T, rng)
    out = {}
    for backend, ref in refiners.items():
        ref.params.tissue_border = True
        try:
            rendered = ref.model_depth(T, 2)
            out[backend] = ref.neighbours(depth, rendered, 2)
            y, _ = ref.measurements(depth, T, 2, rendered)
        finally:
            ref.params.tissue_border = False
        assert out[backend].shape == (len(y), 8)
    np.testing.assert_array_equal(out["numba"], out["numpy"])
    nbrs = out["numba"]
    i, k = np.nonzero(nbrs >= 0)
    assert np.all(nbrs[nbrs[i, k], 7 - k] == i)       # slot k's opposite direction is slot 7 - k
    interior = np.all(nbrs >= 0, axis=1)
    assert 0.5 < interior.mean() < 0.99             # most have all 8; the outline and the invalid pixels' neighbours not
    assert refiners["numba"].neighbours(depth, rendered, 2).shape == (0, 8)   # off: none


def _assert_same_result(a, b):
    """Two RefineResults equal to rounding: the pose within 1e-9 m (the issue's bound is 0.01 mm), H to
    1e-7 relative, the counts and shares exactly, the noise statistics to 1e-9 relative."""
    assert a.converged == b.converged
    np.testing.assert_allclose(b.T_camera_bone, a.T_camera_bone, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.H, a.H, rtol=1e-7, atol=1e-9 * max(np.abs(a.H).max(), 1e-30))
    assert (b.fitness, b.expected, b.confirmed, b.used, b.sharp, b.behind, b.stride) == \
           pytest.approx((a.fitness, a.expected, a.confirmed, a.used, a.sharp, a.behind, a.stride), rel=0, abs=0, nan_ok=True)
    for name in ("rms", "noise", "correlation", "behind_allowed", "behind_mean", "behind_var"):
        assert getattr(b, name) == pytest.approx(getattr(a, name), rel=1e-9, abs=1e-18, nan_ok=True), name


@pytest.mark.parametrize("distance, border, start_width", [(0.42, False, None), (0.8, False, None), (0.42, True, None),
                                                           (0.42, True, 0.0), (0.42, True, 0.04)])
def test_refine_numba_equals_numpy_on_random_poses(refiners, distance, border, start_width, rng, monkeypatch):
    """The whole refinement from 3 mm / 3 deg off: the same pose, information, fitness, shares and noise
    statistics (the numba path's Gauss-Newton loop is one kernel, refine_kernels.gauss_newton); at 0.8 m
    the synthetic crest's small silhouette (~1,160 cells at stride 2) is refined at stride 1; with the
    tissue border (step 5); from the track's width 0 (it stops early and keeps its last association,
    step 8) and from a wide first width (steps that re-render)."""
    for ref in refiners.values():
        monkeypatch.setattr(ref.params, "tissue_border", border)
    for _ in range(4):
        T = _pose(rng, distance)
        depth = _depth(refiners["numpy"], T, rng)
        T0 = T @ se3.from_rotvec_trans(rng.normal(0, 0.03, 3), rng.normal(0, 0.002, 3))
        a, b = (refiners[k].refine(depth, T0, start_width) for k in ("numpy", "numba"))
        assert a.converged
        _assert_same_result(a, b)
        assert se3.translation_distance(b.T_camera_bone, T) < 0.001      # and it converged
        _assert_same_result(*(refiners[k].score(depth, T0) for k in ("numpy", "numba")))
    assert refiners["numba"].choose_stride(T)[0] == (1 if distance > 0.6 else 2)


def test_refine_numba_equals_numpy_when_it_declines(refiners, rng, monkeypatch):
    """Too few pairs in the first step (min_points one above what it uses): both paths decline alike,
    the start pose back, the declined system's H and count."""
    T = _pose(rng)
    depth = _depth(refiners["numpy"], T, rng)
    T0 = T @ se3.from_rotvec_trans(rng.normal(0, 0.03, 3), rng.normal(0, 0.002, 3))
    ref = refiners["numpy"]
    stride, rendered = ref.choose_stride(T0)
    y, z_model, nbrs = ref._measure(depth, T0, stride, rendered)
    p, x, n, d = ref._associate(y, T0)
    used = ref._gn_step(p, x, n, d, ref.sigma(y[:, 2]), 0.0, z_model - y[:, 2], nbrs)[2]
    assert 0 < used < len(y)
    for r in refiners.values():
        monkeypatch.setattr(r.params, "min_points", used + 1)
    a, b = (refiners[k].refine(depth, T0, 0.0) for k in ("numpy", "numba"))
    assert not a.converged and a.used == used
    np.testing.assert_array_equal(a.T_camera_bone, T0)
    _assert_same_result(a, b)


def test_to_bone_and_the_increment_match_se3(rng):
    """The kernel's p = T⁻¹ y and exp(δ)⁻¹ about the centre equal app/geometry/se3.py's, for steps
    large, small and below the exponential's series threshold (1e-8 rad)."""
    from app.filter.refine import Refiner

    center = np.array([0.12, -0.05, 0.3])
    for scale in (0.1, 1e-4, 1e-9, 0.0):
        delta = rng.normal(0, scale, 6) if scale else np.zeros(6)
        M = Refiner._increment(type("R", (), {"center": center})(), delta)
        np.testing.assert_allclose(kernels.increment_inverse(delta, center), se3.inverse(M), rtol=0, atol=1e-15)
    T = _pose(rng)
    y = rng.normal(0, 0.05, (100, 3)) + [0, 0, 0.4]
    np.testing.assert_allclose(kernels.to_bone(y, T), se3.transform_points(se3.inverse(T), y), rtol=0, atol=1e-15)


def test_fill_holes_with_and_without_the_outline_ring(rng):
    """refine.fill_holes (closed form): a covered disc with one-cell holes and a one-cell-wide gap
    across it. Without the ring the holes and the gap take the minimum of their 3x3 neighbourhood and no
    cell outside the disc is covered; with it (the default) the covered cells are the disc grown by the
    3x3 square. The numba kernel equals it on random sparse buffers, both ways."""
    from scipy import ndimage

    from app.filter.refine import fill_holes

    r, c = np.mgrid[0:41, 0:41]
    disc = (r - 20) ** 2 + (c - 20) ** 2 <= 15 ** 2
    zbuf = np.where(disc, 0.4 + 0.001 * r + 0.0001 * c, np.inf)
    holes = [(10, 12), (20, 20), (27, 25)]
    for hr, hc in holes:
        zbuf[hr, hc] = np.inf
    zbuf[:, 30] = np.inf                        # a one-cell-wide gap across the disc
    out = fill_holes(zbuf, ring=False)
    np.testing.assert_array_equal(np.isfinite(out), disc)
    for hr, hc in holes:
        assert out[hr, hc] == zbuf[hr - 1:hr + 2, hc - 1:hc + 2].min()
    grown = fill_holes(zbuf, ring=True)
    np.testing.assert_array_equal(np.isfinite(grown), ndimage.binary_dilation(np.isfinite(zbuf), np.ones((3, 3))))
    for ring in (False, True):
        for _ in range(20):
            sparse = np.where(rng.random((30, 40)) < 0.6, rng.uniform(0.3, 0.5, (30, 40)), np.inf)
            np.testing.assert_array_equal(kernels._fill_holes(sparse, ring), fill_holes(sparse, ring))


def test_ndtr_matches_scipy(rng):
    """The behind moments' Φ (refine_kernels._ndtr, Cephes' form) against scipy.special.ndtr, in the
    centre, the tails and at ±inf."""
    from scipy.special import ndtr

    a = np.concatenate([rng.normal(0, 3, 2000), [-40.0, -8.0, -0.70710678, 0.0, 0.70710678, 8.0, -np.inf, np.inf]])
    got = np.array([kernels._ndtr(v) for v in a])
    np.testing.assert_allclose(got, ndtr(a), rtol=1e-14, atol=1e-300)
