"""The CPU likelihood backend's own parts: the numba pixel term against the numpy reference on random
inputs, numba's cache fallback, the backend choice (render.backend) and the tracker running on it
(its accuracy on a 1.5 s trial is a slow test; the likelihood's equality with GL's is the fast one).
The conformance with the reference and the GL backend: tests/test_backend_conformance.py."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from app.filter import likelihood_ref
from app.filter.likelihood_ref import LikelihoodParams
from app.render import backends, cpu_raster

OPTIONS = [
    {},
    {"occlusion": "smooth_exponential"},
    {"classification": True, "l0_weight": 2.0},
    {"background_ratio": True, "pixel_weight": 0.3},
    {"background_ratio": True, "classification": True, "occlusion": "smooth_exponential", "occluder_margin": 0.005},
]


@pytest.mark.parametrize("option", OPTIONS, ids=lambda o: "-".join(o) or "beam")
def test_the_pixel_term_equals_the_reference_on_random_inputs(option, rng):
    params = replace(LikelihoodParams(), **option)
    z_star = rng.uniform(0.2, 1.2, 400)
    z = z_star + rng.normal(0, 0.004, 400)                       # hits
    z[:100] = rng.uniform(0.05, 2.5, 100)                        # anywhere, beyond z_max too
    z[100:130] = z_star[100:130] - rng.uniform(0.0, 0.05, 30)    # around the occluder margin
    z[130:140] = [0.0, -0.1, np.nan, np.inf, -np.inf, 2.0, 2.0 + 1e-9, 1e-6, 5.0, 0.3]
    reference = likelihood_ref.pixel_log_likelihood(z, z_star, params)
    prm = cpu_raster.pack_params(params)
    ours = np.array([cpu_raster.pixel_log_likelihood(float(a), float(b), prm) for a, b in zip(z, z_star)])
    np.testing.assert_allclose(ours, reference, rtol=1e-9, atol=1e-9)


def _scored_box(z_star, depth, params, product):
    """cpu_raster._score_and_clear over the whole image (a z-buffer of rendered depth z_star), with
    the product path on or off; also checks that it clears the z-buffer."""
    prm = cpu_raster.pack_params(params)
    assert prm[16] == (not params.classification and params.w_u / params.z_max >= likelihood_ref.LOG_FLOOR)
    prm[16] = float(product)
    zbuf = z_star.astype(np.float64)
    exp_lam_z = np.exp(-params.lam * depth.astype(np.float64))
    box = np.array([0, 0, z_star.shape[1] - 1, z_star.shape[0] - 1], np.int64)
    value = cpu_raster._score_and_clear(depth, exp_lam_z, zbuf, box, prm)
    assert not zbuf.any()
    return value


PRODUCT_OPTIONS = [o for o in OPTIONS if not o.get("classification")] + [{"pixel_count_reg": 50.0}]


@pytest.mark.parametrize("option", PRODUCT_OPTIONS, ids=lambda o: "-".join(o) or "beam")
def test_the_sum_by_products_equals_the_sum_of_logs_on_random_images(option, rng):
    """The product path (one log per block of pixels) gives the per-pixel logs' sum and the numpy
    reference's log-likelihood to rounding, on images with hits, occluders, invalid pixels and
    uncovered pixels."""
    params = replace(LikelihoodParams(), **option)
    z_star = rng.uniform(0.3, 0.6, (40, 50)).astype(np.float32)
    z_star[rng.random(z_star.shape) < 0.3] = 0.0                          # not covered
    depth = (z_star + rng.normal(0, 0.002, z_star.shape)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] *= np.float32(0.7)                # occluders in front
    depth[rng.random(depth.shape) < 0.05] = 0.0
    depth[0, :4] = [np.nan, np.inf, 3.0, -1.0]
    reference = float(likelihood_ref.log_likelihood(depth, z_star[None], params)[0])
    by_logs, by_products = _scored_box(z_star, depth, params, False), _scored_box(z_star, depth, params, True)
    assert abs(reference) > 100.0
    assert by_products == pytest.approx(by_logs, rel=1e-12, abs=1e-9)
    assert by_products == pytest.approx(reference, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("extreme", ["huge densities", "tiny densities"])
def test_the_sum_by_products_survives_products_beyond_float64(extreme, rng):
    """Densities whose running product over- or underflows float64 within a few pixels (σ_base = 1e-60:
    p_n ~ 1e59; w_u = 1e-27: p_u = 5e-28 on pixels far from the surface): the product is flushed into
    a log before it leaves [1e-150, 1e150], so the sum stays the per-pixel logs' sum."""
    if extreme == "huge densities":
        params = LikelihoodParams(k=0.0, sigma_base=1e-60)
        z_star = np.full((20, 30), 0.5, np.float32)
        depth = z_star.copy()                                              # every pixel a perfect hit
        factors = params.w_n / (np.sqrt(2 * np.pi) * params.sigma_base)
    else:
        params = LikelihoodParams(w_u=1e-27, w_e=0.0)
        z_star = rng.uniform(0.3, 0.6, (20, 30)).astype(np.float32)
        depth = (z_star + 0.5).astype(np.float32)                          # far behind: density ~ p_u
        factors = params.w_u / params.z_max
    with np.errstate(over="ignore", divide="ignore"):
        assert not np.isfinite(np.log(np.prod(np.full(z_star.size, factors)))), "a plain product must leave float64"
    by_logs, by_products = _scored_box(z_star, depth, params, False), _scored_box(z_star, depth, params, True)
    assert np.isfinite(by_products) and abs(by_logs) > 1e4
    assert by_products == pytest.approx(by_logs, rel=1e-12)
    assert by_products == pytest.approx(float(likelihood_ref.log_likelihood(depth, z_star[None], params)[0]), rel=1e-9)


def test_the_product_path_is_off_where_a_density_could_fall_below_the_log_floor():
    """Classification takes the max of two logs per pixel, and p_u < LOG_FLOOR lets the floor act:
    both keep the per-pixel logs."""
    assert cpu_raster.pack_params(LikelihoodParams())[16] == 1.0
    assert cpu_raster.pack_params(LikelihoodParams(classification=True))[16] == 0.0
    assert cpu_raster.pack_params(LikelihoodParams(w_u=1e-31))[16] == 0.0


def test_without_a_writable_cache_numba_compiles_uncached(monkeypatch, caplog):
    import numba

    real = numba.njit

    def njit(**kwargs):
        if kwargs.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'x.py'")
        return real(**kwargs)

    monkeypatch.setattr(numba, "njit", njit)

    def twice(x):
        return 2 * x

    compiled = cpu_raster._njit()(twice)
    assert compiled(21) == 42 and not compiled._cache.__class__.__name__.endswith("FunctionCache")
    assert "NUMBA_CACHE_DIR" in caplog.text


# GL_RENDERER strings as drivers report them: Mesa's CPU rasterisers, and GPUs (AMD's names LLVM,
# its shader compiler, which is not llvmpipe)
RENDERERS = [
    ("llvmpipe (LLVM 15.0.6, 256 bits)", True),
    ("softpipe", True),
    ("Software Rasterizer", True),
    ("Mesa X11 swrast", True),
    ("NVIDIA H100 80GB HBM3/PCIe/SSE2", False),
    ("AMD Radeon RX 7900 XTX (radeonsi, navi31, LLVM 15.0.7, DRM 3.54, 6.5.0-14-generic)", False),
    ("Mesa Intel(R) UHD Graphics 620 (KBL GT2)", False),
]


@pytest.mark.parametrize("renderer, software", RENDERERS)
def test_the_software_renderer_detection_reads_the_renderer_string(renderer, software):
    from types import SimpleNamespace

    from app.render import context

    assert context.is_software(SimpleNamespace(info={"GL_RENDERER": renderer})) is software


def _gpu_device_nodes() -> list:
    from pathlib import Path

    return sorted(Path("/dev").glob("nvidia[0-9]*")) + sorted(Path("/dev/dri").glob("renderD*"))


def test_auto_picks_the_backend_from_this_machines_real_context(gl_ctx):
    """The real detection on the real context: without any GPU device node (CI, the development
    machines) the context is Mesa's CPU rasteriser and 'auto' picks cpu, naming the renderer; on a
    machine with a GPU the choice follows what its context reports."""
    from app.render import context

    renderer = gl_ctx.info["GL_RENDERER"]
    if not _gpu_device_nodes():
        assert context.is_software(gl_ctx), renderer
    name, why = backends.resolve("auto")
    if context.is_software(gl_ctx):
        assert name == "cpu" and why.startswith("auto: GL is ") and renderer in why
    else:
        assert (name, why) == ("gl", "auto: GL runs on a GPU")
    assert backends.resolve("cpu") == ("cpu", "configured") and backends.resolve("gl") == ("gl", "configured")
    with pytest.raises(ValueError, match="auto, gl, cpu"):
        backends.resolve("vulkan")


def test_auto_falls_back_to_cpu_without_any_gl_context(monkeypatch):
    from app.errors import GLError
    from app.render import context

    def fail():
        raise GLError("no EGL")

    monkeypatch.setattr(context, "shared_context", fail)
    assert backends.resolve("auto") == ("cpu", "auto: no OpenGL context")


def _replay_on_cpu(tmp_path, seconds):
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    simulate(tmp_path / "trial", scenario_name="static_clear", seconds=seconds, seed=11)
    config = replace(load_config(None), backend="cpu")
    result = replay(tmp_path / "trial", tmp_path / "out", config, rrd=False, projector=False)
    return result, json.loads((tmp_path / "out" / "summary.json").read_text())


def test_the_replay_summary_names_the_cpu_backend(tmp_path):
    result, summary = _replay_on_cpu(tmp_path, 0.2)
    assert summary["backend"] == "cpu" and summary["gl"].startswith("cpu backend")
    assert summary["timings_ms"]["cpu_raster_likelihood"] > 0
    assert np.all(np.asarray(result.errors["add_mm"]) < 10.0)     # started 5 mm / 3 deg off


@pytest.mark.slow
def test_the_tracker_on_the_cpu_backend_tracks_a_static_bone(tmp_path):
    """The accuracy bounds of test_tracking_accuracy, with render.backend: cpu."""
    result, _ = _replay_on_cpu(tmp_path, 1.5)
    add = np.asarray(result.errors["add_mm"])
    assert np.median(add[45:]) < 2.5 and np.percentile(add[45:], 95) < 5.0


def _crest_backend(params: LikelihoodParams | None = None):
    """(mesh, backend): the default crest prepared as the tracker prepares it (1,000 triangles, not centred)
    and a one-pose CPU backend on it at 160x120 with tests/test_backend_conformance.py's clip planes."""
    from app.mesh import load_mesh, outward_wound, prepare_mesh
    from app.render.cpu_likelihood import CPULikelihoodBackend
    from app.sim.simulator import DEFAULT_MESH
    from tests.test_backend_conformance import CAMERAS, FAR, NEAR

    mesh = prepare_mesh(load_mesh(DEFAULT_MESH), max_triangles=1000, center=False)
    return mesh, CPULikelihoodBackend(mesh.vertices, mesh.faces, CAMERAS["160x120"], 1, params, near=NEAR, far=FAR,
                                      cull_back_faces=outward_wound(mesh))


@pytest.mark.parametrize("option", ["beam", "background_ratio", "ratio_classification"])
def test_the_fused_evidence_counts_equal_depth_evidence_on_random_inputs(option, rng):
    """CPULikelihoodBackend.evidence (one numba pass over the pose's pixel box) gives the same counts
    as observation.depth_evidence on the backend's own float32 rendering, for random poses (behind the
    camera, off screen, through the near plane, on the border) and measured images with noise,
    occluders, invalid pixels and pixels exactly at the occluder and inlier thresholds."""
    from app.filter.observation import depth_evidence
    from tests.test_backend_conformance import OPTIONS as CASES, measured_image, random_poses, true_pose

    params = replace(LikelihoodParams(), **CASES[option])
    mesh, backend = _crest_backend(params)
    truth = backend.render_depth(true_pose(mesh)[None])[0]
    poses = random_poses(rng, 24, mesh)
    for i in range(3):
        depth = measured_image(truth, rng, params.z_max)
        edge = rng.random(depth.shape) < 0.1            # exactly at the occluder threshold (float32, as numpy)
        depth[edge & (truth > 0)] = (truth - np.float32(params.occluder_margin))[edge & (truth > 0)]
        band = rng.random(depth.shape) < 0.1            # near the 3 σ inlier bound
        sigma = likelihood_ref.noise_sigma(truth.astype(float), params)
        depth[band & (truth > 0)] = (truth + 3.0 * sigma * rng.choice([-1.0, 1.0], truth.shape))[band & (truth > 0)]
        counts = []
        for T in poses:
            want = depth_evidence(backend.render_depth, T, depth, params, 30)
            assert backend.evidence(T, depth, 30) == want
            counts.append(want.covered_pixels)
        assert max(counts) > 300 and min(counts) == 0, "seen and unseen poses both tested"


def test_a_camera_in_a_faces_plane_renders_without_dividing_by_zero():
    """A box over a flat table seen with the camera in the plane of one of its faces: that face's
    interpolated 1 / z is exactly 0 over its bounding box, and numba raised ZeroDivisionError (the
    tracker stopped). Now such pixels are never kept, and the likelihood is finite."""
    import trimesh

    from app.config import load_config
    from app.geometry.camera import PinholeCamera
    from app.pipeline.tracker import DepthTracker

    mesh = trimesh.creation.box((0.08, 0.03, 0.02))
    camera = PinholeCamera(width=160, height=120, K=np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]]))
    T_camera_bone = np.array([[-0.70710678118654791, 0.70710678118654713, 0.0, -0.016011002862997004],
                              [0.70710678118654713, 0.70710678118654791, 1.2246467991473532e-16, 0.040557539631926764],
                              [8.6595605623549279e-17, 8.6595605623549378e-17, -1.0, 0.51],
                              [0.0, 0.0, 0.0, 1.0]])
    assert abs((np.linalg.inv(T_camera_bone) @ [0, 0, 0, 1])[0] + 0.04) < 1e-12     # in the x = -4 cm face's plane
    config = load_config(None)
    tracker = DepthTracker(replace(config, backend="cpu"), mesh, camera)
    ll = tracker.backend.log_likelihood(T_camera_bone[None], np.full((120, 160), 0.5, np.float32))
    assert np.all(np.isfinite(ll))
    tracker.release()


@pytest.mark.parametrize("option", ["beam", "background_ratio", "ratio_classification"])
def test_the_batch_scores_and_renders_each_pose_as_it_does_alone(option, rng):
    """cpu_raster.batch hands the poses out to its chunks one at a time from a shared counter (an
    atomic add): every pose is scored (and rendered) once, bit for bit as in a batch of its own, for
    batches smaller and larger than the chunk count, poses through the near plane and off screen,
    on one numba thread and on all of them."""
    import numba

    from tests.test_backend_conformance import OPTIONS as CASES, measured_image, random_poses, true_pose

    params = replace(LikelihoodParams(), **CASES[option])
    mesh, backend = _crest_backend(params)
    truth = backend.render_depth(true_pose(mesh)[None])[0]
    depth = measured_image(truth, rng, params.z_max)
    poses = np.concatenate([random_poses(rng, 24, mesh), np.repeat(true_pose(mesh)[None], 3, axis=0)])
    alone = np.array([backend.log_likelihood(T[None], depth)[0] for T in poses])
    images = np.concatenate([backend.render_depth(T[None]) for T in poses])
    assert np.all(np.isfinite(alone)) and len(set(alone.tolist())) > 10, "distinct scores tested"
    threads = numba.get_num_threads()
    try:
        for n_threads in sorted({1, threads}):
            numba.set_num_threads(n_threads)
            for n in (1, 3, backend.chunks + 1, len(poses)):
                assert np.array_equal(backend.log_likelihood(poses[:n], depth), alone[:n])
                assert np.array_equal(backend.render_depth(poses[:n]), images[:n])
            assert not backend.zbufs.any(), "the z-buffers are left cleared"
    finally:
        numba.set_num_threads(threads)
    assert backend.log_likelihood(poses[:0], depth).shape == (0,)


def test_the_vertex_transform_is_the_poses_arithmetic_to_the_bit(rng):
    """_render_one's camera-frame vertices and projections (its scratch ``p``, which the evidence pass
    leaves filled) are x = T00 vx + T01 vy + T02 vz + T03 (left to right, as numpy computes it here),
    u = fx x / z + cx with 1 / z, bit for bit: the pose's entries read once per pose change nothing."""
    from tests.test_backend_conformance import NEAR, random_poses

    mesh, backend = _crest_backend()
    depth = np.zeros((120, 160), np.float32)
    vx, vy, vz = backend.vertices[:, 0], backend.vertices[:, 1], backend.vertices[:, 2]
    fx, fy, cx, cy = backend.cam[:4]
    for T in random_poses(rng, 12, mesh):
        backend.evidence(T, depth, 1)
        p = backend._vertex_scratch
        xyz = [T[r, 0] * vx + T[r, 1] * vy + T[r, 2] * vz + T[r, 3] for r in range(3)]
        for r in range(3):
            np.testing.assert_array_equal(p[:, r], xyz[r])
        front = xyz[2] >= NEAR
        iz = 1.0 / xyz[2][front]
        np.testing.assert_array_equal(p[front, 3], fx * xyz[0][front] * iz + cx)
        np.testing.assert_array_equal(p[front, 4], fy * xyz[1][front] * iz + cy)
        np.testing.assert_array_equal(p[front, 5], iz)
