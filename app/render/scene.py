"""Full-resolution rendering of a scene of several meshes from one camera (the simulator's renderer).

Same shaders as the batched renderer (``depth.vert.glsl`` / ``depth.frag.glsl``) with a single
tile: each object is drawn at its own pose with its own label, the depth test resolves what is in
front, and one call returns the linear depth image (metres, 0 = nothing) and the label image
(which object each pixel sees, 0 = nothing).

Usage::

    scene = SceneRenderer(ctx, camera_640x480)
    scene.add_mesh("bone", vertices, faces, label=1)
    depth, labels = scene.render({"bone": T_camera_bone})
"""
from __future__ import annotations

import moderngl
import numpy as np

from app.geometry.camera import PinholeCamera
from app.render import shaders
from app.render.context import unbind_framebuffer
from app.render.batched import DEFAULT_FAR, DEFAULT_NEAR, MeshBuffers, enable_clip_distances
from app.render.glmath import gl_rows_to_image, mat4_to_glsl


class SceneRenderer:
    """Render named meshes at given poses into one depth image and one label image.

    Parameters
    ----------
    ctx : moderngl.Context
    camera : PinholeCamera of the output images
    near, far : clip planes in metres
    """

    MAX_OBJECTS = 64

    def __init__(self, ctx: moderngl.Context, camera: PinholeCamera, near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR):
        self.ctx = ctx
        self.camera = camera
        size = (int(camera.width), int(camera.height))
        self.program = shaders.program(ctx, "depth.vert.glsl", "depth.frag.glsl")
        self.program["projection"].write(mat4_to_glsl(camera.opengl_projection(near, far)))
        self.program["grid"].value = (1, 1)
        self.poses = ctx.buffer(reserve=64 * self.MAX_OBJECTS)
        self.depth_texture = ctx.texture(size, 1, dtype="f4")
        self.label_texture = ctx.texture(size, 1, dtype="f4")
        self.zbuffer = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer(color_attachments=[self.depth_texture, self.label_texture], depth_attachment=self.zbuffer)
        self.meshes: dict[str, tuple[MeshBuffers, int]] = {}

    def add_mesh(self, name: str, vertices: np.ndarray, faces: np.ndarray, label: int) -> None:
        """Register a mesh (object frame, metres) under ``name`` with an integer ``label`` > 0."""
        if name in self.meshes:
            self.meshes[name][0].release()
        self.meshes[name] = (MeshBuffers(self.ctx, self.program, vertices, faces), int(label))

    def render(self, T_camera_object: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) float32 metres and labels (H, W) int32 of the named objects at their poses.

        Objects not named in ``T_camera_object`` are not drawn.
        """
        names = [name for name in T_camera_object if name in self.meshes]
        missing = set(T_camera_object) - set(self.meshes)
        if missing:
            raise KeyError(f"no mesh registered for {sorted(missing)}; known: {sorted(self.meshes)}")
        poses = np.stack([T_camera_object[name] for name in names]) if names else np.zeros((0, 4, 4))
        if len(poses):
            self.poses.write(mat4_to_glsl(poses))
        self.poses.bind_to_storage_buffer(0)
        self.fbo.use()
        self.fbo.viewport = (0, 0, *self.depth_texture.size)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        enable_clip_distances(self.ctx)
        for i, name in enumerate(names):
            mesh, label = self.meshes[name]
            self.program["first_instance"].value = i
            self.program["label"].value = float(label)
            mesh.vao.render(moderngl.TRIANGLES, instances=1)
        h, w = self.camera.height, self.camera.width
        depth = np.frombuffer(self.depth_texture.read(), dtype=np.float32).reshape(h, w)
        labels = np.frombuffer(self.label_texture.read(), dtype=np.float32).reshape(h, w)
        return gl_rows_to_image(depth), gl_rows_to_image(labels).astype(np.int32)

    def release(self) -> None:
        unbind_framebuffer(self.ctx)
        for mesh, _ in self.meshes.values():
            mesh.release()
        for obj in (self.fbo, self.zbuffer, self.depth_texture, self.label_texture, self.poses, self.program):
            obj.release()
