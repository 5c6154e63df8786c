"""``osteonav simulate``: write a complete recorded trial of a simulated operating-room scene.

A UR5e moves a flange-mounted depth camera (640x480 at 90 Hz, RealSense D415-like intrinsics;
joint samples at 500 Hz) over a bone lying on a table inside soft tissue so that only the crest
protrudes. Moving occluders (a hand whose edge is placed to cover a target fraction of the bone's
visible pixels, an instrument) cross the view; the bone may be repositioned; frames drop; the
depth image gets the errors of the chosen depth sensor model (:mod:`app.sim.sensors`: ``independent`` by
default, ``stereo``, ``tof``; named in trial.yaml's ``sensor`` block). Rendering uses the project's
own :class:`app.render.scene.SceneRenderer`, so simulated and tracked depth share one camera model.

With ``streams`` including ``ir`` and/or ``color`` it also writes the left imager's infrared image
(with the D415's dot pattern when ``emitter``) and the colour camera's image of every frame (trial
format 1.1), rendered through the appearance model of :mod:`app.sim.appearance` and
:mod:`app.sim.images`; depth alone (version 1) stays the default.

Besides the trial format's files it writes ``simulation.csv`` (per frame: occlusion fraction,
visible bone pixels), ``simulation.yaml`` (scenario, seed, the true hand-eye) and ``camera_truth.txt``
(the camera's true poses, TUM rows; :mod:`app.sim.truth`); readers of the format ignore them.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import trimesh
import yaml

from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.geometry.ur import UR_MODELS, forward_kinematics
from app.sim import world
from app.sim.scenarios import Scenario, get_scenario
from app.sim.sensors import DEFAULT_SENSOR, SceneErrors, parse_sensor, sensor_to_dict
from app.sim.truth import CAMERA_TRUTH_FILE
from app.outputs import wrote
from app.trial.tum import write_tum

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
DEFAULT_MESH = REPO / "meshes" / "iliac_crest.ply"
D415_640x480 = PinholeCamera(
    K=np.array([[612.4, 0.0, 318.9], [0.0, 612.0, 241.3], [0.0, 0.0, 1.0]]), width=640, height=480
)
FPS = 90.0
JOINT_RATE = 500.0
DEPTH_SCALE_MM = 0.1
CLOCK_START = 100.0          # s, arbitrary start of the shared clock
LABEL_BONE, LABEL_TISSUE, LABEL_TABLE, LABEL_HAND, LABEL_INSTRUMENT = 1, 2, 3, 4, 5
GRAFT_SIZE = np.array([0.020, 0.010, 0.010])   # m, along bone x, y, z


@dataclass
class SimulationSummary:
    out: str
    scenario: str
    frames: int
    seconds: float
    mean_occlusion: float
    max_occlusion: float


def frame_schedule(scenario: Scenario, rng: np.random.Generator, fps: float = FPS) -> tuple[np.ndarray, np.ndarray]:
    """Frame counters and stamps after random drops and scenario gaps."""
    n = int(round(scenario.seconds * fps))
    frame_ids = np.arange(n)
    t = frame_ids / fps
    keep = rng.random(n) >= scenario.drop_probability
    keep[0] = True
    for start, duration in scenario.gaps:
        keep &= ~((t >= start) & (t < start + duration))
    return frame_ids[keep], CLOCK_START + t[keep]


def perturb_pose(T: np.ndarray, mm: float, deg: float, rng: np.random.Generator) -> np.ndarray:
    """T with a translation of ``mm`` and a rotation of ``deg`` about random directions (bone frame origin)."""
    if mm == 0 and deg == 0:
        return T.copy()
    direction = rng.normal(size=3)
    axis = rng.normal(size=3)
    out = T.copy()
    out[:3, 3] += mm * 1e-3 * direction / np.linalg.norm(direction)
    out[:3, :3] = quat.to_matrix(quat.exp_map(np.deg2rad(deg) * axis / np.linalg.norm(axis))) @ T[:3, :3]
    return out


def target_occlusion(scenario: Scenario, t: float) -> float:
    """The hand's target fraction of the bone's visible pixels at scenario time ``t``."""
    if scenario.full_occlusion and scenario.full_occlusion[0] <= t < sum(scenario.full_occlusion):
        return 1.0
    if not scenario.occlusion_profile:
        return 0.0
    knots = np.array(scenario.occlusion_profile)
    return float(np.interp(t, knots[:, 0], knots[:, 1]))


class _GraftCut:
    """Depth of the crest after a graft (box in the bone frame at the crest's top) is cut out."""

    def __init__(self, bone: trimesh.Trimesh):
        top = bone.vertices[np.argmax(bone.vertices[:, 2])]
        self.centre = np.array([top[0], top[1], top[2] - GRAFT_SIZE[2] / 2])
        self.half = GRAFT_SIZE / 2

    def apply(self, depth, labels, T_camera_bone, camera: PinholeCamera) -> np.ndarray:
        rows, cols = np.nonzero(labels == LABEL_BONE)
        if len(rows) == 0:
            return depth
        rays = np.linalg.solve(camera.K, np.stack([cols, rows, np.ones_like(cols)]).astype(float)).T
        p_camera = rays * depth[rows, cols, None]
        T_bone_camera = se3.inverse(T_camera_bone)
        p_bone = p_camera @ T_bone_camera[:3, :3].T + T_bone_camera[:3, 3]
        inside = np.all(np.abs(p_bone - self.centre) <= self.half, axis=1)
        if not inside.any():
            return depth
        # new surface: the graft floor, plane z_bone = centre_z - half_z, intersected with each ray
        n_camera = T_camera_bone[:3, 2]
        floor_point = T_camera_bone[:3, :3] @ (self.centre - [0, 0, self.half[2]]) + T_camera_bone[:3, 3]
        s = (n_camera @ floor_point) / (rays[inside] @ n_camera)
        out = depth.copy()
        out[rows[inside], cols[inside]] = np.maximum(s, depth[rows[inside], cols[inside]])
        return out


def simulate(out: str | Path, mesh_path: str | Path | None = None, scenario_name: str | Scenario = "static_occluded",
             seconds: float | None = None, seed: int = 0, overwrite: bool = False,
             camera: PinholeCamera = D415_640x480, progress=None, streams: str = "depth",
             emitter: bool = True, sensor=DEFAULT_SENSOR, pointer=None) -> SimulationSummary:
    """Simulate ``scenario_name`` and write the trial to ``out`` (see the module docstring).

    streams : 'depth' or e.g. 'depth,ir,color' (:func:`app.sim.images.parse_streams`)
    emitter : whether the infrared image shows the dot projector's pattern
    sensor : the depth sensor model: a model of :mod:`app.sim.sensors`, or its name or
        ``NAME:KEY=VALUE,...`` text (:func:`app.sim.sensors.parse_sensor`); default ``independent``
    pointer : an :class:`app.sim.pointer.SimulatedPointer` held on the crest, its marker drawn into the
        infrared images (``streams`` must include ``ir``), or None

    The random draws come from ``seed`` in one fixed order (the bone's pose, the frame drops, the tissue,
    the calibration errors, the joints, then each frame's sensor noise), and the image streams from a
    stream of their own, so a depth-only trial is the same with or without them.
    """
    from app.sim.images import parse_streams
    from app.trial.writer import TrialWriter

    stream_names = parse_streams(streams)
    if pointer is not None and "ir" not in stream_names:
        raise ValueError(f"a simulated pointer is drawn into the infrared images: streams must include ir, got {streams!r}")
    sensor = parse_sensor(sensor) if isinstance(sensor, str) else sensor
    if seconds is not None and not 0 < seconds < float("inf"):   # 0 never means "the scenario's default"
        raise ValueError(f"seconds must be a finite duration > 0 (None: the scenario's), got {seconds!r}")
    if isinstance(scenario_name, Scenario):
        scenario = replace(scenario_name, seconds=seconds) if seconds else scenario_name
    else:
        scenario = get_scenario(scenario_name, seconds)
    rng = np.random.default_rng(seed)
    scene = _Scene.build(scenario, Path(mesh_path) if mesh_path else DEFAULT_MESH, camera, rng)
    images = _image_simulator(stream_names, emitter, scene.bone, scene.T_base_bone[0], camera,
                              np.random.default_rng([seed, 14]), scene.objects)   # its own stream: depth-only trials unchanged
    meta, drawing = _trial_meta(scene, sensor, images, pointer, seed, rng)
    out = Path(out)
    with TrialWriter(out, meta, mesh_source=scene.mesh_path, overwrite=overwrite) as writer:
        _write_joints(writer, scene.stamps, scenario, rng)
        occlusions = _write_frames(writer, out, scene, sensor, images, drawing, rng, progress)
        wrote(out / CAMERA_TRUTH_FILE)
        write_tum(out / CAMERA_TRUTH_FILE, scene.stamps, scene.T_base_camera)
        _write_simulation_yaml(out, scenario, seed, scene.T_flange_camera, scene.mesh_path, sensor, drawing)
    scene.renderer.release()
    if images is not None:
        images.release()
    log.info("simulated %s: %d frames in %s", scenario.name, len(scene.stamps), out)
    return SimulationSummary(str(out), scenario.name, len(scene.stamps), scenario.seconds,
                             float(np.mean(occlusions)), float(np.max(occlusions)))


@dataclass
class _Scene:
    """The simulated world of one trial: the bone and its tissue on the table, their poses and the camera's at
    every frame (base frame), and the renderer holding their meshes."""

    scenario: Scenario
    mesh_path: Path
    bone: trimesh.Trimesh
    camera: PinholeCamera
    dh: object
    T_flange_camera: np.ndarray
    frame_ids: np.ndarray
    stamps: np.ndarray
    t_rel: np.ndarray               # s since the clock's start, per frame
    T_base_bone: np.ndarray         # (N, 4, 4) the bone's true pose per frame
    T_base_camera: np.ndarray       # (N, 4, 4) the camera's true pose per frame
    T_base_table: np.ndarray
    objects: tuple
    renderer: object

    @classmethod
    def build(cls, scenario: Scenario, mesh_path: Path, camera: PinholeCamera, rng: np.random.Generator) -> "_Scene":
        """Draws from ``rng``: the bone's initial pose, the frame schedule, then the soft tissue, in that order."""
        from app.mesh import check_units, load_mesh
        from app.render.context import shared_context
        from app.render.scene import SceneRenderer

        bone = load_mesh(mesh_path)
        check_units(bone, mesh_path)
        dh = UR_MODELS["ur5e"]
        T_flange_camera = world.T_FLANGE_CAMERA
        T_base_bone0 = world.initial_bone_pose(dh, T_flange_camera, rng, scenario.camera_distance_m,
                                               scenario.bone_yaw_deg)
        frame_ids, stamps = frame_schedule(scenario, rng)
        t_rel = stamps - CLOCK_START
        T_base_bone = world.bone_trajectory(t_rel, T_base_bone0, scenario.bone_motion)
        T_base_camera = forward_kinematics(dh, world.joint_trajectory(t_rel)) @ T_flange_camera
        # the table 6 cm below the bone's lowest point, in the base frame (z up)
        T_base_table = np.eye(4)
        T_base_table[2, 3] = (T_base_bone0[:3, :3] @ bone.vertices.T).T[:, 2].min() + T_base_bone0[2, 3] - 0.06
        tissue = world.soft_tissue_mesh(bone, rng)
        renderer = SceneRenderer(shared_context(), camera)
        objects = (("bone", bone, LABEL_BONE), ("tissue", tissue, LABEL_TISSUE),
                   ("table", world.table_mesh(), LABEL_TABLE), ("hand", world.hand_mesh(), LABEL_HAND),
                   ("instrument", world.instrument_mesh(), LABEL_INSTRUMENT))
        for name, mesh, label in objects:
            renderer.add_mesh(name, mesh.vertices, mesh.faces, label)
        return cls(scenario, mesh_path, bone, camera, dh, T_flange_camera, frame_ids, stamps, t_rel, T_base_bone,
                   T_base_camera, T_base_table, objects, renderer)


def _trial_meta(scene: _Scene, sensor, images, pointer, seed: int, rng: np.random.Generator):
    """(the trial's :class:`app.trial.meta.TrialMeta`, the pointer's drawing or None): the hand-eye and the
    initial pose as a user would give them, with the scenario's errors (drawn from ``rng`` in that order),
    and the point prior at the crest's top."""
    from app.trial.meta import TrialMeta

    scenario = scene.scenario
    hand_eye_in_file = perturb_pose(scene.T_flange_camera, scenario.hand_eye_error_mm, scenario.hand_eye_error_deg, rng)
    initial_pose = perturb_pose(scene.T_base_bone[0], scenario.init_error_mm, scenario.init_error_deg, rng)
    top = scene.bone.vertices[np.argmax(scene.bone.vertices[:, 2])]
    point_prior = scene.T_base_bone[0, :3, :3] @ top + scene.T_base_bone[0, :3, 3]
    drawing = None
    if pointer is not None:
        from app.sim.pointer import PointerDrawing

        drawing = PointerDrawing.held(pointer, point_prior, scene.T_base_bone[0], scene.T_base_camera[0],
                                      np.random.default_rng([seed, 33]))
    meta = TrialMeta(
        camera=scene.camera, depth_scale=DEPTH_SCALE_MM, robot={"model": "ur5e"}, dh=scene.dh,
        T_flange_camera=hand_eye_in_file, mesh=scene.mesh_path.name, initial_pose=initial_pose,
        point_prior=point_prior, extra={"sensor": sensor_to_dict(sensor)}, streams=images.streams if images else None,
    )
    return meta, drawing


def _write_frames(writer, out: Path, scene: _Scene, sensor, images, drawing, rng: np.random.Generator,
                  progress) -> list[float]:
    """Render, measure and write every frame (depth, images, ground truth, a ``simulation.csv`` row); the
    occluded fraction of the bone per frame."""
    scenario = scene.scenario
    errors = SceneErrors(invalid_probability=scenario.invalid_probability, scale_error=scenario.depth_scale_error,
                         bias=scenario.depth_bias_m, specular_fraction=scenario.specular_fraction)
    graft = _GraftCut(scene.bone)
    occlusions = []
    wrote(out / "simulation.csv")
    with open(out / "simulation.csv", "w") as sim_csv:
        sim_csv.write("frame,stamp,occlusion,bone_pixels\n")
        for k, (frame_id, stamp) in enumerate(zip(scene.frame_ids, scene.stamps)):
            T_camera_base = se3.inverse(scene.T_base_camera[k])
            T_camera_bone = T_camera_base @ scene.T_base_bone[k]
            poses = {"bone": T_camera_bone, "tissue": T_camera_bone, "table": T_camera_base @ scene.T_base_table}
            depth, labels, bone_mask = _render_frame(scene, poses, float(scene.t_rel[k]), graft, T_camera_bone)
            measured = sensor.measure(depth, rng, camera=scene.camera, depth_scale_mm=DEPTH_SCALE_MM, errors=errors,
                                      bone_mask=labels == LABEL_BONE)
            n_bone = int(bone_mask.sum())
            occlusion = 1.0 - float((bone_mask & (labels == LABEL_BONE)).sum()) / n_bone if n_bone else 1.0
            occlusions.append(occlusion)
            ir = rgb = None
            if images is not None:
                ir, rgb = images.frame(depth, labels, poses, T_camera_base, float(scene.t_rel[k]))
            if drawing is not None:
                ir = drawing.draw(ir, scene.camera, T_camera_bone)
            writer.write_frame(int(frame_id), float(stamp), measured, infrared=ir, color=rgb)
            writer.write_groundtruth(float(stamp), scene.T_base_bone[k])
            sim_csv.write(f"{frame_id},{stamp:.6f},{occlusion:.4f},{n_bone}\n")
            if progress:
                progress(k + 1, len(scene.stamps))
    return occlusions


def _render_frame(scene: _Scene, poses: dict, t: float, graft: "_GraftCut", T_camera_bone: np.ndarray):
    """(true depth, labels, the bone's pixels without occluders) of one frame at scenario time ``t``: the scene
    rendered clear, the occluders placed on that view (``poses`` gets theirs), rendered again; then the graft's
    cut and the tissue patch when the scenario has them."""
    scenario = scene.scenario
    _, labels_clear = scene.renderer.render(poses)
    bone_mask = labels_clear == LABEL_BONE
    _add_occluders(poses, scenario, t, bone_mask, scene.camera)
    depth, labels = scene.renderer.render(poses)
    if scenario.graft_cut_at_s is not None and t >= scenario.graft_cut_at_s:
        depth = graft.apply(depth, labels, T_camera_bone, scene.camera)
    if scenario.tissue_patch_m:
        depth = _tissue_patch(depth, labels, scene.camera, scenario.tissue_patch_m)
    return depth, labels, bone_mask


class _FrameImages:
    """The simulator's hook for the image streams: the IR and colour images of one rendered frame."""

    LABEL_OF = {"bone": LABEL_BONE, "tissue": LABEL_TISSUE, "table": LABEL_TABLE, "hand": LABEL_HAND,
                "instrument": LABEL_INSTRUMENT}

    def __init__(self, sim, color_renderer):
        self.sim = sim
        self.color_renderer = color_renderer
        self.streams = sim.streams

    def frame(self, depth, labels, poses: dict, T_camera_base: np.ndarray, t: float):
        by_label = {self.LABEL_OF[name]: T for name, T in poses.items()}
        ir = self.sim.infrared(depth, labels, by_label, T_camera_base, t) if self.sim.with_ir else None
        rgb = None
        if self.sim.with_color:
            rgb = self.sim.color(self.color_renderer.render, poses, self.LABEL_OF, T_camera_base, t)
        return ir, rgb

    def release(self) -> None:
        if self.color_renderer is not None:
            self.color_renderer.release()


def _image_simulator(stream_names, emitter: bool, bone, T_base_bone0: np.ndarray, camera: PinholeCamera,
                     rng: np.random.Generator, objects) -> _FrameImages | None:
    """The IR/colour image hook for ``stream_names``, or None for depth alone."""
    if stream_names == ("depth",):
        return None
    from app.render.context import shared_context
    from app.render.scene import SceneRenderer
    from app.sim.appearance import OperatingField
    from app.sim.images import ImageSimulator

    scene = OperatingField(rng, bone.bounds, T_base_bone0[:3, 3])
    sim = ImageSimulator(scene, camera, rng, emitter=emitter, with_ir="ir" in stream_names,
                         with_color="color" in stream_names)
    color_renderer = None
    if sim.with_color:
        color_renderer = SceneRenderer(shared_context(), sim.color_camera)
        for name, mesh, label in objects:
            color_renderer.add_mesh(name, mesh.vertices, mesh.faces, label)
    return _FrameImages(sim, color_renderer)


def _write_joints(writer, stamps: np.ndarray, scenario: Scenario, rng: np.random.Generator) -> None:
    """Joint samples at 500 Hz covering every frame, stamped on the robot's clock (offset, jitter)."""
    t_robot = np.arange(stamps[0] - 0.02, stamps[-1] + 0.02, 1.0 / JOINT_RATE)
    t_true = t_robot - scenario.clock_offset_s
    q = world.joint_trajectory(t_true - CLOCK_START)
    q = q + rng.normal(0.0, scenario.encoder_noise_rad, q.shape)
    writer.write_joints(t_robot, q)


def _add_occluders(poses: dict, scenario: Scenario, t: float, bone_mask: np.ndarray, camera: PinholeCamera) -> None:
    fraction = target_occlusion(scenario, t)
    if fraction > 0 and bone_mask.any():
        rows, cols = np.nonzero(bone_mask)
        u_edge = cols.max() + 20.0 if fraction >= 1.0 else float(np.quantile(cols, fraction))
        poses["hand"] = world.hand_pose_for_fraction(u_edge, float(rows.mean()), camera.fx, camera.fy, camera.cx, camera.cy)
    if scenario.instrument:
        poses["instrument"] = world.instrument_pose(t)


def _tissue_patch(depth: np.ndarray, labels: np.ndarray, camera: PinholeCamera, thickness: float) -> np.ndarray:
    """Residual soft tissue of ``thickness`` m on the left third of the bone's visible pixels."""
    rows, cols = np.nonzero(labels == LABEL_BONE)
    if len(cols) == 0:
        return depth
    patch = cols < np.quantile(cols, 0.33)
    out = depth.copy()
    out[rows[patch], cols[patch]] -= thickness
    return out


def _write_simulation_yaml(out: Path, scenario: Scenario, seed: int, T_flange_camera_true: np.ndarray, mesh_path: Path,
                           sensor, pointer=None) -> None:
    info = {
        "generator": "osteonav simulate",
        "scenario": _plain(asdict(scenario)),
        "seed": int(seed),
        "mesh_source": str(mesh_path),
        "sensor": _plain(sensor_to_dict(sensor)),
        "true_hand_eye": T_flange_camera_true.tolist(),
    }
    if pointer is not None:       # the tool drawn into the infrared images and where its tip touches
        info["pointer"] = {**_plain(pointer.tool.session_block()), "off_m": float(pointer.tool.off_m),
                           "tip_base": [float(v) for v in pointer.tip_base]}
    wrote(out / "simulation.yaml")
    (out / "simulation.yaml").write_text(yaml.safe_dump(info, sort_keys=False))


def _plain(value):
    """Tuples to lists, numpy scalars to floats, recursively (for yaml.safe_dump)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
