"""What the simulated operating field looks like: materials, their textures on the objects, the light.

Not a segmentation: each object's albedo varies over its own surface (textures fixed in the
object's frame, so they move with it), the light is a surgical lamp that sways and dims, and
wet tissue shows specular highlights that saturate the sensor.

- **bone** (label 1): whitish-yellow cortical bone with periosteum-covered (pinkish) patches and
  blood stains (dark red), in the bone frame;
- **soft tissue** (label 2): muscle (red) and fat (yellow) mixed over the surface, pools of blood,
  and a white gauze swab (woven, blood-soaked spots) lying beside the crest;
- **table** (3): the surgical drape (blue-green); **hand** (4): pale glove with smears of blood;
  **instrument** (5): steel, very specular.

Reflectance is Lambert plus Blinn-Phong (Phong 1975; Blinn 1977):
``L = albedo * (ambient + E cos(theta_i)) + k_s E cos(theta_h)^n``, with ``E`` the lamp's irradiance
``I(t) spot(phi) / d^2`` (spot falloff ``cos(phi)^m`` about the lamp's axis), times a smooth, slowly
drifting field for the uneven light of the room (other lamps, reflections off drapes and gowns).
Textures are band-limited 3-D "Fourier noise" (a sum of random plane waves, Perlin's use of
noise for texture, 1985) evaluated at the surface point in the object's frame.

Used by :mod:`app.sim.images` (camera exposure, colour and infrared images) and the simulator.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry import se3
from app.geometry.camera import PinholeCamera

LABEL_NAMES = {1: "bone", 2: "tissue", 3: "table", 4: "hand", 5: "instrument"}


@dataclass(frozen=True)
class Material:
    """Linear-RGB diffuse albedo, near-infrared reflectance (850 nm), specular weight and exponent."""

    albedo: tuple[float, float, float]
    nir: float
    specular: float
    shininess: float


MATERIALS = {
    "bone": Material((0.80, 0.71, 0.50), 0.78, 0.30, 40.0),
    "periosteum": Material((0.70, 0.44, 0.40), 0.66, 0.30, 30.0),
    "blood": Material((0.28, 0.02, 0.02), 0.55, 0.55, 80.0),      # wet clot: dark red, bright in NIR
    "muscle": Material((0.40, 0.05, 0.045), 0.50, 0.40, 50.0),
    "fat": Material((0.86, 0.68, 0.30), 0.80, 0.25, 30.0),
    "gauze": Material((0.95, 0.95, 0.92), 0.92, 0.02, 4.0),
    "glove": Material((0.92, 0.87, 0.76), 0.88, 0.20, 20.0),
    "drape": Material((0.07, 0.28, 0.36), 0.40, 0.05, 10.0),
    "steel": Material((0.55, 0.56, 0.58), 0.60, 0.90, 150.0),
}


class FourierNoise:
    """A smooth random field on R^3, about N(0, 1): n(p) = sum_k a_k cos(w_k . p + phi_k) / sqrt(sum_k a_k^2 / 2).

    ``scale_m`` is the typical feature size: |w_k| ~ 2 pi / scale_m (log-normal spread); with
    ``octaves`` > 1, octave o adds waves of twice the frequency at half the amplitude (fractal
    Brownian motion), which gives stains and patches irregular, ragged edges instead of blobs.
    """

    def __init__(self, rng: np.random.Generator, scale_m: float, n_waves: int = 8, octaves: int = 1):
        k = n_waves * octaves
        directions = rng.normal(size=(k, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        octave = np.repeat(np.arange(octaves), n_waves)
        freq = 2 * np.pi / scale_m * 2.0 ** octave * np.exp(rng.normal(0.0, 0.35, k))
        self.w = (directions * freq[:, None]).T.astype(np.float32)       # (3, K)
        self.phi = rng.uniform(0, 2 * np.pi, k).astype(np.float32)
        amp = 0.5 ** octave
        self.amp = (amp / np.sqrt(np.sum(amp ** 2) / 2.0)).astype(np.float32)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """Field values (M,) at points p (M, 3), metres (float32: the phases stay within a few hundred rad)."""
        phase = np.asarray(p, np.float32) @ self.w
        phase += self.phi
        np.cos(phase, out=phase)
        return phase @ self.amp


def _mix(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    return a * (1 - weight[:, None]) + b * weight[:, None]


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _material_rows(name: str, n: int) -> np.ndarray:
    """(n, 6): albedo r, g, b, nir, specular, shininess of one material."""
    m = MATERIALS[name]
    return np.tile(np.array([*m.albedo, m.nir, m.specular, m.shininess]), (n, 1))


class SurfaceTextures:
    """Per-pixel material parameters from each pixel's object label and its point in the object's frame."""

    def __init__(self, rng: np.random.Generator, bone_bounds: np.ndarray):
        self.periosteum = FourierNoise(rng, 0.016, octaves=2)
        self.stain = FourierNoise(rng, 0.014, octaves=3)
        self.fat = FourierNoise(rng, 0.022, octaves=3)
        self.pool = FourierNoise(rng, 0.014, octaves=2)
        self.fine = FourierNoise(rng, 0.0015, n_waves=16)
        self.smear = FourierNoise(rng, 0.008, octaves=2)
        fibre = rng.normal(size=3) * [1.0, 0.3, 0.2]    # muscle fibres run roughly along the crest
        self.fibre_w = (2 * np.pi / 0.0012 * fibre / np.linalg.norm(fibre)).astype(np.float32)
        lo, hi = np.asarray(bone_bounds, float)
        extent = hi - lo
        centre = (lo + hi) / 2
        # a gauze swab beside the crest, on the tissue (bone frame, x along the crest, z up)
        self.gauze_centre = centre[:2] + np.array([0.25 * extent[0], -(extent[1] / 2 + 0.022)])
        self.gauze_half = np.array([0.030, 0.018])

    def materials(self, label: int, p_object: np.ndarray) -> np.ndarray:
        """(M, 6) material rows (see :func:`_material_rows`) for points p_object (M, 3) of ``label``."""
        n = len(p_object)
        name = LABEL_NAMES.get(int(label), "drape")
        if name in ("table", "instrument"):   # uniform drape and steel: no texture to evaluate
            return _material_rows("steel" if name == "instrument" else "drape", n)
        if name == "bone":
            rows = _material_rows("bone", n)
            rows = _mix(rows, _material_rows("periosteum", n), 0.8 * _smoothstep(self.periosteum(p_object), 0.4, 1.2))
            rows = _mix(rows, _material_rows("blood", n), 0.85 * _smoothstep(self.stain(p_object), 1.2, 1.9))
        elif name == "tissue":
            muscle = _material_rows("muscle", n)
            muscle[:, :4] *= 0.86 + 0.14 * np.cos(np.asarray(p_object, np.float32) @ self.fibre_w)[:, None] ** 2
            rows = _mix(muscle, _material_rows("fat", n), _smoothstep(self.fat(p_object), 0.4, 1.1))
            rows = _mix(rows, _material_rows("blood", n), 0.9 * _smoothstep(self.pool(p_object), 1.3, 2.0))
            rows = self._gauze(rows, p_object)
        elif name == "hand":
            rows = _mix(_material_rows("glove", n), _material_rows("blood", n), 0.7 * _smoothstep(self.smear(p_object), 1.6, 2.2))
        rows[:, :4] *= 1.0 + 0.05 * self.fine(p_object)[:, None]
        return rows

    def _gauze(self, rows: np.ndarray, p_bone: np.ndarray) -> np.ndarray:
        d = np.abs(p_bone[:, :2] - self.gauze_centre) - self.gauze_half
        inside = np.maximum(d[:, 0], d[:, 1]) < 0
        if not inside.any():
            return rows
        p = p_bone[inside]
        weave = 0.92 + 0.08 * np.abs(np.sin(np.pi * p[:, 0] / 0.0008) * np.sin(np.pi * p[:, 1] / 0.0008))
        gauze = _material_rows("gauze", len(p))
        gauze[:, :4] *= weave[:, None]
        gauze = _mix(gauze, _material_rows("blood", len(p)), 0.8 * _smoothstep(self.stain(p * 0.7), 1.0, 1.8))
        rows[inside] = gauze
        return rows


@dataclass(frozen=True)
class Lamp:
    """A surgical lamp above the field (robot base frame, z up), swaying and dimming with time.

    position(t) = p0 + sway * (sin(2 pi f1 t), cos(2 pi f2 t), 0); it points at ``target``;
    intensity(t) = 1 + 0.12 sin(2 pi 0.21 t + phase) - 0.25 [a dip while someone's head passes].
    """

    p0: np.ndarray
    target: np.ndarray
    sway_m: float = 0.12
    f1: float = 0.07
    f2: float = 0.05
    phase: float = 0.0
    spot_exponent: float = 6.0
    dip: tuple[float, float] = (1.2, 0.8)   # start, duration s

    def position(self, t: float) -> np.ndarray:
        return self.p0 + self.sway_m * np.array([np.sin(2 * np.pi * self.f1 * t + self.phase),
                                                 np.cos(2 * np.pi * self.f2 * t), 0.0])

    def intensity(self, t: float) -> float:
        dip = 0.25 if self.dip[0] <= t < sum(self.dip) else 0.0
        return 1.0 + 0.12 * np.sin(2 * np.pi * 0.21 * t + self.phase) - dip


def surface_normals(camera: PinholeCamera, depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals in the camera frame facing the camera, from central differences of the points.

    n = (dP/du x dP/dv) / |...| with P(u, v) = depth(u, v) K^-1 (u, v, 1); (0, 0, -1) where undefined.
    """
    p = camera.pixel_rays().astype(np.float32) * depth[..., None].astype(np.float32)
    du = np.zeros_like(p)
    dv = np.zeros_like(p)
    du[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dv[1:-1] = p[2:] - p[:-2]
    n = np.cross(du, dv)
    norm = _length(n)
    ok = (norm[..., 0] > 1e-12) & (depth > 0)
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-12), np.array([0.0, 0.0, -1.0]))
    flip = np.sum(n * p, axis=-1) > 0     # face the camera
    n[flip] *= -1
    return n


def _length(v: np.ndarray) -> np.ndarray:
    """|v| over the last axis, kept as (..., 1)."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]


def smooth_light_field(shape: tuple[int, int], t: float, phase: np.ndarray) -> np.ndarray:
    """(H, W) multiplicative field ~[0.8, 1.2], smooth across the image and drifting slowly with t."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    x, y = u / w, v / h
    field = (0.10 * np.sin(2 * np.pi * (0.6 * x + 0.3 * y) + phase[0] + 0.4 * t)
             + 0.07 * np.sin(2 * np.pi * (-0.4 * x + 0.8 * y) + phase[1] - 0.3 * t)
             + 0.05 * np.cos(2 * np.pi * 1.3 * x + phase[2] + 0.2 * t))
    return 1.0 + field


def shade(camera: PinholeCamera, depth: np.ndarray, labels: np.ndarray, rows: np.ndarray, p_lamp_camera: np.ndarray,
          axis_camera: np.ndarray, lamp: Lamp, intensity: float, ambient: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (H, W, 3) and NIR-reflectance-weighted (H, W) radiance of the visible surfaces.

    rows : (H, W, 6) material rows (albedo rgb, nir, specular, shininess); depth 0 = background (black).
    The camera sits at the origin, so the view direction of a point p is -p / |p|.
    """
    f32 = np.float32
    p = camera.pixel_rays().astype(f32) * depth[..., None].astype(f32)
    n = surface_normals(camera, depth)
    to_lamp = p_lamp_camera.astype(f32) - p
    d2 = np.maximum(np.einsum("...i,...i->...", to_lamp, to_lamp), 1e-6)
    l = to_lamp / np.sqrt(d2)[..., None]
    view = -p / np.maximum(_length(p), 1e-9)
    h = l + view
    h /= np.maximum(_length(h), 1e-9)
    cos_i = np.clip(np.einsum("...i,...i->...", n, l), 0.0, None)
    cos_h = np.clip(np.einsum("...i,...i->...", n, h), 0.0, None)
    spot = np.clip(-(l @ axis_camera.astype(f32)), 0.0, None) ** lamp.spot_exponent
    E = intensity * spot / d2          # lamp at ~1 m: E ~ 1
    diffuse = ambient + E * cos_i
    specular = rows[..., 4] * E * cos_h ** rows[..., 5] * (cos_i > 0)
    rgb = rows[..., :3] * diffuse[..., None] + specular[..., None]
    nir = rows[..., 3] * diffuse + specular
    empty = depth <= 0
    rgb[empty] = 0.0
    nir[empty] = 0.0
    return rgb, nir


class OperatingField:
    """The scene's appearance: textures, lamp and room light, for one simulated trial (one seed)."""

    def __init__(self, rng: np.random.Generator, bone_bounds: np.ndarray, p_base_bone: np.ndarray):
        self.textures = SurfaceTextures(rng, bone_bounds)
        target = np.asarray(p_base_bone, float)
        self.lamp = Lamp(p0=target + np.array([0.25, -0.15, 1.0]), target=target, phase=float(rng.uniform(0, 2 * np.pi)))
        self.field_phase = rng.uniform(0, 2 * np.pi, 3)
        self.ambient = 0.18

    def material_image(self, depth: np.ndarray, labels: np.ndarray, camera: PinholeCamera,
                       T_camera_object: dict[int, np.ndarray]) -> np.ndarray:
        """(H, W, 6) material rows for every pixel, each textured in its own object's frame."""
        rows = np.zeros(depth.shape + (6,), np.float32)
        rays = camera.pixel_rays().astype(np.float32)
        for label in np.unique(labels):
            if label <= 0:
                continue
            mask = (labels == label) & (depth > 0)
            if LABEL_NAMES.get(int(label)) in ("table", "instrument", None):
                rows[mask] = self.textures.materials(int(label), np.zeros((int(mask.sum()), 3)))
                continue
            p_camera = rays[mask] * depth[mask, None]
            T = T_camera_object.get(int(label))
            if T is not None:
                T_object_camera = se3.inverse(T).astype(np.float32)
                p_object = p_camera @ T_object_camera[:3, :3].T + T_object_camera[:3, 3]
            else:
                p_object = p_camera
            rows[mask] = self.textures.materials(int(label), p_object)
        return rows

    def radiance(self, camera: PinholeCamera, depth: np.ndarray, labels: np.ndarray,
                 T_camera_object: dict[int, np.ndarray], T_camera_base: np.ndarray, t: float, rows=None):
        """Linear RGB (H, W, 3) and grey near-infrared (H, W) scene radiance seen by ``camera`` at time t.

        rows : the (H, W, 6) :meth:`material_image` when already computed
        """
        rows = self.material_image(depth, labels, camera, T_camera_object) if rows is None else rows
        p_lamp = T_camera_base[:3, :3] @ self.lamp.position(t) + T_camera_base[:3, 3]
        axis_base = self.lamp.target - self.lamp.position(t)
        axis = T_camera_base[:3, :3] @ (axis_base / np.linalg.norm(axis_base))
        d0 = np.linalg.norm(axis_base)
        rgb, nir = shade(camera, depth, labels, rows, p_lamp, axis, self.lamp, self.lamp.intensity(t) * d0 * d0,
                         self.ambient)
        field = smooth_light_field(depth.shape, t, self.field_phase)
        return rgb * field[..., None], nir * field
