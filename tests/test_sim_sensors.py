"""The simulator's depth sensor models (app/sim/sensors/) against closed forms on synthetic scenes.

Pure numpy: exact depth images of planes and steps go through each model; nothing is rendered.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from app.geometry.camera import PinholeCamera
from app.sim.sensors import (SENSORS, SceneErrors, get_sensor, parse_sensor, sensor_from_dict, sensor_label,
                             sensor_to_dict)
from app.sim.sensors.common import quantise_depth
from app.sim.sensors.independent import IndependentSensor
from app.sim.sensors.stereo import StereoSensor, right_image_hidden
from app.sim.sensors.tof import TofSensor, incidence_cosine

F_PX = 612.4
DEPTH_SCALE_MM = 0.1
NO_DROPOUTS = SceneErrors(invalid_probability=0.0)


def camera(width: int, height: int) -> PinholeCamera:
    return PinholeCamera(np.array([[F_PX, 0.0, width / 2], [0.0, F_PX, height / 2], [0.0, 0.0, 1.0]]), width, height)


def plane(z: float, width: int = 320, height: int = 120) -> np.ndarray:
    return np.full((height, width), z)


def step(width: int = 320, height: int = 60, z_bg: float = 0.6, z_fg: float = 0.4, cols=(200, 260)) -> np.ndarray:
    """A background plane with a foreground bar over columns [cols[0], cols[1]) of every row."""
    depth = np.full((height, width), z_bg)
    depth[:, cols[0]:cols[1]] = z_fg
    return depth


def frames(model, depth, n: int, seed: int = 0, errors=NO_DROPOUTS) -> np.ndarray:
    rng = np.random.default_rng(seed)
    cam = camera(depth.shape[1], depth.shape[0])
    return np.stack([model.measure(depth, rng, camera=cam, depth_scale_mm=DEPTH_SCALE_MM, errors=errors)
                     for _ in range(n)]).astype(np.float64)


def lag1_correlation(measured: np.ndarray, z: float) -> float:
    """Correlation of the depth errors of horizontally adjacent valid pixels (one frame)."""
    e = measured - z
    ok = (measured[:, 1:] > 0) & (measured[:, :-1] > 0)
    a, b = e[:, 1:][ok], e[:, :-1][ok]
    return float(np.corrcoef(a, b)[0, 1])


# ------------------------------------------------------------------ independent: today's model, unchanged

def _apply_sensor_before_the_registry(depth, model, rng, bone_mask=None):
    """Frozen copy of app/sim/sensor.py's ``apply_sensor`` as it was before the sensor models (commit fbcebb2)."""
    from app.sim.sensors.common import depth_edges, smooth_field

    valid = depth > 0
    z = depth.astype(np.float64) * (1.0 + model["scale_error"])
    if model["bias"]:
        h, w = depth.shape
        v, u = np.mgrid[0:h, 0:w]
        z = z + model["bias"] * (0.6 * np.cos(np.pi * u / w) + 0.4 * np.sin(np.pi * v / h))
    z = z + rng.standard_normal(z.shape) * (0.0015 * z * z + 0.0003)
    invalid = ~valid | (z < 0.28) | (z > 3.0)
    edges = depth_edges(np.where(valid, depth, 0.0), 0.006)
    edges = ndimage.binary_dilation(edges, iterations=1)
    invalid |= edges
    invalid |= rng.random(z.shape) < model["invalid_probability"]
    if model["specular_fraction"] > 0 and bone_mask is not None and bone_mask.any():
        field = smooth_field(depth.shape, rng, scale_px=4.0)
        threshold = np.quantile(field[bone_mask], 1.0 - model["specular_fraction"])
        invalid |= bone_mask & (field > threshold)
    return np.where(invalid, 0.0, z).astype(np.float32)


@pytest.mark.parametrize("errors", [SceneErrors(), SceneErrors(0.02, 0.005, 0.001, 0.15)])
def test_independent_model_is_bit_identical_to_the_simulator_before_sensor_models(errors):
    depth = step(z_bg=0.5, z_fg=0.42)
    depth[:5, :40] = 0.0            # empty pixels
    bone = np.zeros(depth.shape, bool)
    bone[10:50, 210:250] = True
    rng_old, rng_new = np.random.default_rng(7), np.random.default_rng(7)
    old = _apply_sensor_before_the_registry(depth, errors.__dict__, rng_old, bone)
    new = IndependentSensor().measure(depth, rng_new, errors=errors, bone_mask=bone)
    assert new.dtype == old.dtype == np.float32
    assert np.array_equal(old, new)
    assert rng_old.random() == rng_new.random()    # the same draws: the rest of a trial is unchanged too


def test_independent_noise_is_k_z2_plus_base_and_uncorrelated():
    z = 0.42
    measured = frames(IndependentSensor(), plane(z), 20)
    expected = IndependentSensor().sigma(z)
    assert expected == pytest.approx(0.0015 * z * z + 0.0003)
    assert np.std(measured - z) == pytest.approx(expected, rel=0.02)
    assert abs(lag1_correlation(measured[0], z)) < 0.03


# ------------------------------------------------------------------ stereo

@pytest.mark.parametrize("z", [0.42, 0.65])
def test_stereo_per_pixel_depth_noise_is_z2_sigma_d_over_f_b(z):
    """Per pixel over frames: sigma_z = z^2 sigma_d / (f b) (sigma_d with the 1/32 px rounding's variance),
    and the 0.1 mm depth unit's rounding variance (0.1 mm)^2 / 12."""
    model = StereoSensor()
    measured = frames(model, plane(z), 30)
    valid = np.all(measured > 0, axis=0)
    assert valid.sum() > 0.5 * valid.size
    per_pixel_var = np.var(measured[:, valid], axis=0, ddof=1)
    closed_form = np.sqrt(model.sigma_z(z, F_PX) ** 2 + (DEPTH_SCALE_MM * 1e-3) ** 2 / 12)
    assert model.sigma_z(z, F_PX) == pytest.approx(z * z * np.hypot(0.08, 1 / 32 / np.sqrt(12)) / (F_PX * 0.055))
    assert np.sqrt(per_pixel_var.mean()) == pytest.approx(closed_form, rel=0.04)
    assert np.mean(measured[:, valid]) == pytest.approx(z, abs=0.1 * closed_form)   # unbiased


def test_stereo_noise_is_correlated_over_the_matching_window():
    """Lag-1 correlation (w - 1) / w of the disparity noise (6/7 for 7 px), diluted only by the roundings'
    independent variances; the independent model's is ~0."""
    z, model = 0.42, StereoSensor()
    measured = frames(model, plane(z), 1)[0]
    sigma_fb = z * z * model.sigma_d_px / (F_PX * model.baseline_m)
    total = model.sigma_z(z, F_PX) ** 2 + (DEPTH_SCALE_MM * 1e-3) ** 2 / 12
    expected = (model.window_px - 1) / model.window_px * sigma_fb ** 2 / total
    assert lag1_correlation(measured, z) == pytest.approx(expected, abs=0.03)
    wide = frames(StereoSensor(window_px=11), plane(z), 1)[0]
    assert lag1_correlation(wide, z) > lag1_correlation(measured, z) + 0.03
    assert abs(lag1_correlation(frames(IndependentSensor(), plane(z), 1)[0], z)) < 0.03


def test_stereo_shadow_lies_left_of_the_foreground_and_is_d_fg_minus_d_bg_wide():
    """The right imager (+x) cannot see the background just left of a nearer bar: columns u with
    u - d_bg >= 200 - d_fg. Right of the bar nothing is hidden; the image's left band u < d_bg is."""
    fb = F_PX * 0.055
    depth = step()
    hidden = right_image_hidden(fb / depth)
    first_shadow = int(np.ceil(200 - fb / 0.4 + fb / 0.6))          # 172
    assert hidden[:, first_shadow:200].all()
    assert not hidden[:, int(np.ceil(fb / 0.6)):first_shadow].any()
    assert not hidden[:, 200:].any()                                # the bar and everything right of it
    assert hidden[:, :int(fb / 0.6)].all()                          # left band: no match in the right image
    measured = frames(StereoSensor(), depth, 1)[0]
    assert (measured[:, first_shadow:198] == 0).all()
    assert (measured[:, 265:] > 0).mean() > 0.99                    # no shadow on the right side


def test_stereo_edges_are_invalid_or_flying_within_the_band():
    """Within 2 px of the bar's right edge (no shadow there): ~60 % invalid, the rest flying between the
    two surfaces; away from edges neither."""
    model = StereoSensor()
    measured = frames(model, step(), 20)
    band = measured[:, :, 258:262]                                   # 2 px either side of the edge at 260
    invalid = band == 0
    assert invalid.mean() == pytest.approx(model.edge_invalid_fraction, abs=0.05)
    between = (band > 0.41) & (band < 0.59)
    assert between.mean() > 0.2                                      # flying pixels
    assert not ((measured[:, :, 270:] > 0.41) & (measured[:, :, 270:] < 0.59)).any()
    assert (measured[:, :, 270:] > 0).all()


def test_stereo_depth_is_quantised_to_the_depth_unit_and_disparity_to_1_32_px():
    """Depth in whole 16-bit units of depth_scale (steps of exactly one unit without the disparity rounding);
    with it, every depth is f b / (k / 32) in whole units: steps of ~z^2 / (32 f b) = 0.23 mm at 0.5 m."""
    unrounded = frames(StereoSensor(subpixel_levels=0), plane(0.5), 1)
    units = unrounded[unrounded > 0] * 1e3 / DEPTH_SCALE_MM
    assert np.allclose(units, np.rint(units), atol=1e-3)
    assert np.min(np.diff(np.unique(np.rint(units)))) == 1           # steps of exactly one depth unit
    z = frames(StereoSensor(), plane(0.5), 2)
    z = z[z > 0]
    units = z * 1e3 / DEPTH_SCALE_MM
    assert np.allclose(units, np.rint(units), atol=1e-3)
    fb = F_PX * 0.055
    assert np.median(np.diff(np.unique(np.rint(units)))) * DEPTH_SCALE_MM == pytest.approx(
        0.5 ** 2 / (32 * fb) * 1e3, abs=DEPTH_SCALE_MM)
    k = np.rint(fb / z * 32)                                         # the disparity, in 1/32 px
    assert np.allclose(quantise_depth(fb / (k / 32), DEPTH_SCALE_MM), z, atol=1e-7)
    coarse = frames(StereoSensor(depth_unit_mm=1.0), plane(0.5), 1)
    mm = coarse[coarse > 0] * 1e3
    assert np.allclose(mm, np.rint(mm), atol=1e-3)


def test_stereo_applies_the_scenario_errors_like_every_model():
    depth = plane(0.42)
    bone = np.zeros(depth.shape, bool)
    bone[20:100, 150:300] = True
    errors = SceneErrors(invalid_probability=0.05, scale_error=0.01, specular_fraction=0.2)
    measured = StereoSensor().measure(depth, np.random.default_rng(3), camera=camera(320, 120),
                                      depth_scale_mm=DEPTH_SCALE_MM, errors=errors, bone_mask=bone)
    visible = ~right_image_hidden(np.full(depth.shape, F_PX * 0.055 / 0.42))
    lost = measured == 0
    assert lost[~bone & visible].mean() == pytest.approx(0.05, abs=0.01)
    assert lost[bone & visible].mean() == pytest.approx(1 - 0.95 * 0.8, abs=0.03)
    assert np.median(measured[measured > 0]) == pytest.approx(0.42 * 1.01, abs=1e-4)


def test_stereo_out_of_range_is_invalid():
    assert (frames(StereoSensor(), plane(0.25), 1) == 0).all()        # disparity above the 126 px search range
    assert (frames(StereoSensor(), plane(3.5), 1) == 0).all()


# ------------------------------------------------------------------ time of flight

def tilted_plane(z0: float, angle_deg: float, width: int = 320, height: int = 120):
    """Depth of a plane through (0, 0, z0) whose normal is turned ``angle_deg`` about the camera's y axis,
    and the closed-form |cos| of each pixel's incidence angle."""
    cam = camera(width, height)
    a = np.deg2rad(angle_deg)
    n = np.array([np.sin(a), 0.0, -np.cos(a)])
    v, u = np.mgrid[0:height, 0:width].astype(float)
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
    depth = (n @ [0.0, 0.0, z0]) / (rays @ n)
    return depth, np.abs(rays @ n) / np.linalg.norm(rays, axis=-1)


def test_incidence_cosine_of_a_tilted_plane_is_exact():
    depth, cos = tilted_plane(0.5, 60.0)
    assert np.allclose(incidence_cosine(depth, camera(320, 120)), cos, atol=1e-9)


@pytest.mark.parametrize("z, angle", [(0.42, 0.0), (0.65, 0.0), (0.5, 60.0)])
def test_tof_noise_is_sigma_ref_over_sqrt_amplitude_and_uncorrelated(z, angle):
    """Per pixel over frames: sigma_z = sigma_ref (z / z_ref) / sqrt(cos theta) (with the depth unit's
    rounding variance); a tilted plane's noise grows by 1 / sqrt(cos 60 deg) = 1.41."""
    model = TofSensor(multipath_bias_m=0.0)
    depth, cos = tilted_plane(z, angle)
    measured = frames(model, depth, 30)
    valid = np.all(measured > 0, axis=0)
    assert valid.mean() > 0.99
    var = np.var(measured[:, valid], axis=0, ddof=1)
    expected = model.sigma_z(depth[valid], cos[valid]) ** 2 + (DEPTH_SCALE_MM * 1e-3) ** 2 / 12
    assert np.sqrt(var.mean()) == pytest.approx(np.sqrt(expected.mean()), rel=0.03)
    if angle == 0.0:
        assert model.sigma_z(z) == pytest.approx(0.001 * z / 0.5)
        assert abs(lag1_correlation(measured[0], z)) < 0.03


def test_tof_grazing_surfaces_are_invalid_below_the_amplitude_threshold():
    model = TofSensor()
    depth, cos = tilted_plane(0.5, 88.0, width=64, height=32)
    amp = model.amplitude(depth, cos)
    measured = frames(model, depth, 1)[0]
    in_range = (depth > model.z_min + 0.01) & (depth < model.z_max - 0.1)
    dim, bright = in_range & (amp < 0.8 * model.min_amplitude), in_range & (amp > 1.25 * model.min_amplitude)
    assert dim.sum() > 100 and bright.sum() > 100
    assert (measured[dim] == 0).all() and (measured[bright] > 0).all()


def test_tof_mixes_the_two_surfaces_at_a_discontinuity_and_casts_no_shadow():
    """The pixels either side of the bar's edges lie between the two depths (amplitude-weighted mixtures),
    none is invalid for it; nothing is hidden left of the bar as in stereo."""
    model = TofSensor(multipath_bias_m=0.0)
    measured = frames(model, step(), 20)
    edge = measured[:, :, [199, 200, 259, 260]]
    assert (edge > 0).mean() > 0.99
    assert ((edge > 0.4 + 0.003) & (edge < 0.6 - 0.003)).mean() > 0.8
    assert (edge > 0.4 - 0.005).all() and (edge < 0.6 + 0.005).all()
    # amplitude weighting: with c ~ U(0, 1), the mean mixture lies nearer the (brighter) foreground
    assert np.mean(edge) < 0.5
    assert (measured[:, :, 170:198] > 0).mean() > 0.99


def test_tof_multipath_bias_decays_away_from_discontinuities():
    """Mean error r px from the edge (outside the mixed pixels): multipath_bias_m exp(-r / multipath_px)."""
    model = TofSensor()
    measured = frames(model, step(), 20)
    # right of the bar (background at 0.6 m): column 260 is the first background pixel, 0.5 px from the jump
    for k in (1, 2, 4, 7):
        column = measured[:, :, 260 + k]
        expected = model.multipath_bias_m * np.exp(-(k + 0.5) / model.multipath_px)
        sem = model.sigma_z(0.6) / np.sqrt(column.size)
        assert np.mean(column) - 0.6 == pytest.approx(expected, abs=4 * sem + 0.03e-3)
    assert np.mean(measured[:, :, 300:]) - 0.6 == pytest.approx(0.0, abs=0.1e-3)


def test_tof_depth_is_quantised_to_the_depth_unit():
    measured = frames(TofSensor(), plane(0.5), 1)
    units = measured[measured > 0] * 1e3 / DEPTH_SCALE_MM
    assert np.allclose(units, np.rint(units), atol=1e-3)
    assert np.min(np.diff(np.unique(np.rint(units)))) == 1


# ------------------------------------------------------------------ registry

def test_every_registered_model_measures_a_plane_near_its_depth():
    for name in SENSORS:
        measured = frames(get_sensor(name), plane(0.45), 1)[0]
        assert (measured > 0).mean() > 0.4, name
        assert np.median(measured[measured > 0]) == pytest.approx(0.45, abs=5e-4), name


def test_unknown_model_or_parameter_is_refused_with_the_valid_list():
    with pytest.raises(ValueError, match="unknown sensor model 'kinect'; valid: independent, stereo, tof"):
        get_sensor("kinect")
    with pytest.raises(ValueError, match="no parameter 'window'.*window_px"):
        parse_sensor("stereo:window=9")
    with pytest.raises(ValueError, match="expected NAME or NAME:KEY=VALUE"):
        parse_sensor("stereo:window_px")
    with pytest.raises(ValueError, match="window_px expects a number"):
        parse_sensor("stereo:window_px=wide")
    with pytest.raises(ValueError, match="window_px=2.5"):
        parse_sensor("stereo:window_px=2.5")
    with pytest.raises(ValueError, match="edge_dilation=-1"):
        parse_sensor("independent:edge_dilation=-1")
    with pytest.raises(ValueError, match="z_min=0.5"):
        parse_sensor("tof:z_min=0.5,z_max=0.4")


def test_a_model_round_trips_through_its_trial_yaml_block_and_is_labelled():
    model = parse_sensor("stereo:window_px=9,sigma_d_px=0.1")
    assert model == StereoSensor(window_px=9, sigma_d_px=0.1) and isinstance(model.window_px, int)
    block = sensor_to_dict(model)
    assert block["model"] == "stereo" and block["window_px"] == 9
    assert sensor_from_dict(block) == model
    assert sensor_label(StereoSensor()) == "stereo"
    assert sensor_label(model).startswith("stereo-") and sensor_label(model) != sensor_label(StereoSensor(window_px=9))
    with pytest.raises(ValueError, match="expected a mapping with 'model'"):
        sensor_from_dict({"window_px": 9})
