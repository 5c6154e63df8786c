"""Batched depth rendering of N pose hypotheses in one instanced draw.

(A) III.C, (B) 4.3-4.4, DESIGN.md "Rendering all hypotheses at once": the decimated mesh is drawn
N times in one ``glDrawElementsInstanced`` call; instance i reads its pose ``T_camera_bone[i]``
from a storage buffer and lands in tile i of a ``(cols * w) x (rows * h)`` float texture that holds
*linear* camera depth in metres (0 where the pose does not cover a pixel), with the depth test on.
Each instance is clipped to its own tile with four clip distances (the tile's clip-space square),
so nothing bleeds into a neighbour.

The texture stays on the GPU for the likelihood compute shader (:mod:`app.render.likelihood`);
:meth:`BatchedDepthRenderer.read_depth` reads tiles back as image-ordered arrays for tests, the
numpy reference and diagnostics.

Usage::

    renderer = BatchedDepthRenderer(ctx, vertices_bone, faces, camera_80x60, capacity=200)
    renderer.render(T_camera_bone)          # (N, 4, 4)
    depth = renderer.read_depth(len(T_camera_bone))   # (N, 60, 80) float32, metres
"""
from __future__ import annotations

import logging

import moderngl
import numpy as np

from app.geometry.camera import PinholeCamera
from app.render import shaders
from app.render.context import unbind_framebuffer
from app.render.glmath import gl_rows_to_image, mat4_to_glsl, tile_grid

log = logging.getLogger(__name__)

GL_CLIP_DISTANCE0 = 0x3000
DEFAULT_NEAR = 0.05  # m: closer than any D415 measurement (min range ~0.3 m)
DEFAULT_FAR = 4.0  # m


def enable_clip_distances(ctx: moderngl.Context, count: int = 4) -> None:
    """glEnable(GL_CLIP_DISTANCEi) for i < count (moderngl has no flag for them)."""
    for i in range(count):
        ctx.enable_direct(GL_CLIP_DISTANCE0 + i)


class MeshBuffers:
    """Vertex and index buffers of one triangle mesh, with a vertex array for ``program``."""

    def __init__(self, ctx: moderngl.Context, program: moderngl.Program, vertices, faces):
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"expected vertices (V, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
        self.n_faces = len(faces)
        self.vbo = ctx.buffer(vertices.tobytes())
        self.ibo = ctx.buffer(faces.tobytes())
        self.vao = ctx.vertex_array(program, [(self.vbo, "3f", "in_position")], self.ibo, index_element_size=4)

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo):
            obj.release()


class BatchedDepthRenderer:
    """Render N poses of one mesh into a tiled linear-depth texture.

    Parameters
    ----------
    ctx : moderngl.Context
    vertices : (V, 3) float, mesh vertices in the bone frame, metres
    faces : (F, 3) int, triangle indices
    camera : PinholeCamera at the filter's resolution (tile size = camera.width x camera.height)
    capacity : maximum number of poses per call
    near, far : clip planes in metres
    cull_back_faces : skip triangles facing away from the camera (about 2.5x faster on llvmpipe);
        only valid for a mesh whose triangles wind counter-clockwise seen from outside
        (:func:`app.mesh.outward_wound`)
    """

    def __init__(
        self,
        ctx: moderngl.Context,
        vertices: np.ndarray,
        faces: np.ndarray,
        camera: PinholeCamera,
        capacity: int,
        near: float = DEFAULT_NEAR,
        far: float = DEFAULT_FAR,
        cull_back_faces: bool = False,
    ):
        self.ctx = ctx
        self.camera = camera
        self.flags = moderngl.DEPTH_TEST | (moderngl.CULL_FACE if cull_back_faces else 0)
        self.capacity = int(capacity)
        self.tile_w, self.tile_h = int(camera.width), int(camera.height)
        self.grid = tile_grid(self.capacity, self.tile_w, self.tile_h)
        size = (self.grid[0] * self.tile_w, self.grid[1] * self.tile_h)
        max_size = ctx.info["GL_MAX_TEXTURE_SIZE"]
        if max(size) > max_size:
            raise ValueError(f"{capacity} tiles of {self.tile_w}x{self.tile_h} need a {size} texture; the GL limit is {max_size}")
        self.program = shaders.program(ctx, "depth.vert.glsl", "depth.frag.glsl")
        self.program["projection"].write(mat4_to_glsl(camera.opengl_projection(near, far)))
        self.program["grid"].value = self.grid
        self.program["label"].value = 1.0
        self.mesh = MeshBuffers(ctx, self.program, vertices, faces)
        self.poses = ctx.buffer(reserve=64 * self.capacity)
        self.depth_texture = ctx.texture(size, 1, dtype="f4")
        self.depth_texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.zbuffer = ctx.depth_renderbuffer(size)
        # depth only: the fragment shader's label output has no attachment here and is discarded
        self.fbo = ctx.framebuffer(color_attachments=[self.depth_texture], depth_attachment=self.zbuffer)
        self.n_rendered = 0

    @property
    def texture_size(self) -> tuple[int, int]:
        return self.depth_texture.size

    def render(self, T_camera_bone: np.ndarray) -> None:
        """Render the mesh at each pose into its tile (the texture stays on the GPU).

        Parameters
        ----------
        T_camera_bone : (N, 4, 4) float, poses of the bone in the OpenCV camera frame, N <= capacity
        """
        n = len(T_camera_bone)
        if n > self.capacity:
            raise ValueError(f"{n} poses but the renderer was built for at most {self.capacity}")
        self.poses.write(mat4_to_glsl(T_camera_bone))
        self.poses.bind_to_storage_buffer(0)
        self.fbo.use()
        self.fbo.viewport = (0, 0, *self.texture_size)
        # only the tile rows the n poses use are cleared (and read back): one pose costs one row
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=self._rows_region(n))
        self.ctx.enable_only(self.flags)
        self.ctx.front_face = "ccw"
        self.ctx.cull_face = "back"
        enable_clip_distances(self.ctx)
        self.program["first_instance"].value = 0
        self.mesh.vao.render(moderngl.TRIANGLES, instances=n)
        self.n_rendered = n

    def read_depth(self, n: int | None = None) -> np.ndarray:
        """Read back the first ``n`` tiles as (n, h, w) float32 depth images (image row order)."""
        n = self.n_rendered if n is None else n
        if n > self.n_rendered:
            raise ValueError(f"{n} tiles asked but only {self.n_rendered} rendered")
        cols = self.grid[0]
        region = self._rows_region(n)
        rows = region[3] // self.tile_h
        data = np.frombuffer(self.fbo.read(viewport=region, components=1, dtype="f4"), dtype=np.float32)
        big = data.reshape(rows * self.tile_h, cols * self.tile_w)
        tiles = big.reshape(rows, self.tile_h, cols, self.tile_w).transpose(0, 2, 1, 3).reshape(-1, self.tile_h, self.tile_w)
        return gl_rows_to_image(tiles[:n])

    def _rows_region(self, n: int) -> tuple[int, int, int, int]:
        """(x, y, w, h) GL region of the tile rows holding tiles 0..n-1 (tile row r spans y = r h ..)."""
        rows = max(1, -(-n // self.grid[0]))
        return (0, 0, self.texture_size[0], rows * self.tile_h)

    def release(self) -> None:
        unbind_framebuffer(self.ctx)
        for obj in (self.fbo, self.zbuffer, self.depth_texture, self.poses, self.program):
            obj.release()
        self.mesh.release()
