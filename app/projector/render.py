"""The template seen from the projector: moderngl, two passes, lines of a width in millimetres.

The projector is an inverse camera (:mod:`app.projector.model`), so the image it must show is the
image a camera at the projector would see of the plan drawn on the bone:

1. **Bone depth.** The bone mesh at ``T_projector_bone`` is rendered with the depth test into a
   float texture of linear depth (z in the projector frame, metres; 0 = no bone), through the same
   OpenCV -> OpenGL flip and K-based projection as the tracker's renderer
   (:meth:`PinholeCamera.opengl_projection`).
2. **Ribbons.** Each plan segment becomes a flat quad ``line_width`` wide lying in the bone's
   tangent plane (side vector = surface normal x segment direction), plus a small disc at every
   polyline vertex so corners close. A ribbon fragment is lit only where the bone depth exists and
   the ribbon is not behind the bone surface by more than ``depth_tolerance``: outline parts on the
   far side of the crest, hidden by the bone, and anything off the bone stay black; so do parts
   where the surface is seen at grazing incidence (beyond ``max_incidence_deg``).

Because the ribbons lie on the bone, the drawn line is ``line_width`` wide *on the bone* whatever
the distance and incidence (a grazing surface gets a thin line in the image, as it should).

Output: (H, W, 3) uint8, bright outline (``color``) on black, row 0 at the top (the projector's
pixel (u, v) = (column, row)). GL state and resources live in one object; call ``release()``.
"""
from __future__ import annotations

import moderngl
import numpy as np

from app.projector.geometry import MAX_INCIDENCE_DEG, closest_points_on_mesh
from app.projector.model import ProjectorModel
from app.projector.plan import Plan
from app.render import shaders
from app.render.context import unbind_framebuffer
from app.render.glmath import gl_rows_to_image, mat4_to_glsl

LINE_WIDTH_M = 0.001
DEPTH_TOLERANCE_M = 0.0015
"""A ribbon fragment up to this far behind the bone surface still counts as on it (the ribbon is
flat, the bone curved, and depth is interpolated differently on the two): well below the crest's
thickness, so the far side of the crest stays hidden."""
NEAR_M, FAR_M = 0.05, 3.0
DISC_SEGMENTS = 8
DEFAULT_COLOR = (0, 255, 0)


def ribbon_triangles(plan: Plan, vertices: np.ndarray, faces: np.ndarray, width: float = LINE_WIDTH_M
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the plan's ribbons and corner discs, and the surface normal at each corner, bone frame.

    Parameters
    ----------
    plan : outline polylines on the bone (bone frame, metres)
    vertices, faces : the bone mesh, for the surface normals
    width : line width on the bone, metres

    Returns
    -------
    triangles : (T, 3, 3) float32 triangle corners, bone frame, metres
    normals : (T, 3, 3) float32 unit surface normals at those corners, bone frame
    """
    import trimesh

    normals_f = trimesh.Trimesh(vertices, faces, process=False).face_normals
    half = 0.5 * float(width)
    tris, norms = [], []
    for line in plan.polylines:
        _, _, face = closest_points_on_mesh(line, vertices, faces)
        n = normals_f[face]
        a, b = line[:-1], line[1:]
        na, nb = n[:-1], n[1:]
        d = b - a
        keep = np.linalg.norm(d, axis=1) > 1e-9
        a, b, d, na, nb = a[keep], b[keep], d[keep], na[keep], nb[keep]
        side = np.cross(0.5 * (na + nb), d)
        side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-12)
        side *= half
        a0, a1, b0, b1 = a - side, a + side, b - side, b + side
        tris.append(np.stack([a0, b0, b1], axis=1))
        tris.append(np.stack([a0, b1, a1], axis=1))
        norms.append(np.stack([na, nb, nb], axis=1))
        norms.append(np.stack([na, nb, na], axis=1))
        # discs at the vertices, in each vertex's tangent plane
        e1 = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(n, e1)
        ang = np.linspace(0.0, 2 * np.pi, DISC_SEGMENTS + 1)
        ring = half * (np.cos(ang)[None, :, None] * e1[:, None] + np.sin(ang)[None, :, None] * e2[:, None])
        centre = np.repeat(line[:, None], DISC_SEGMENTS, axis=1)
        tris.append(np.stack([centre, line[:, None] + ring[:, :-1], line[:, None] + ring[:, 1:]], axis=2).reshape(-1, 3, 3))
        norms.append(np.repeat(n[:, None, None, :], DISC_SEGMENTS, axis=1).repeat(3, axis=2).reshape(-1, 3, 3))
    return np.concatenate(tris).astype(np.float32), np.concatenate(norms).astype(np.float32)


class ProjectorRenderer:
    """Renders a plan on the bone from the projector's viewpoint (see the module docstring).

    Parameters
    ----------
    ctx : moderngl.Context (app.render.context.shared_context() or create_context())
    projector : ProjectorModel (K_p and resolution are used; the pose comes with each call)
    vertices, faces : the bone mesh, bone frame, metres (the occluder and the surface for the lines)
    plan : outline on the bone
    line_width : metres on the bone
    color : (r, g, b) 0..255 of the outline
    depth_tolerance : metres, see DEPTH_TOLERANCE_M
    max_incidence_deg : see MAX_INCIDENCE_DEG
    """

    def __init__(self, ctx: moderngl.Context, projector: ProjectorModel, vertices: np.ndarray, faces: np.ndarray,
                 plan: Plan, line_width: float = LINE_WIDTH_M, color=DEFAULT_COLOR,
                 depth_tolerance: float = DEPTH_TOLERANCE_M, max_incidence_deg: float = MAX_INCIDENCE_DEG):
        if not line_width > 0:
            raise ValueError(f"line_width must be > 0 metres, got {line_width}")
        self.ctx = ctx
        self.projector = projector
        self.plan = plan
        self.line_width = float(line_width)
        size = (projector.width, projector.height)
        projection = mat4_to_glsl(projector.camera.opengl_projection(NEAR_M, FAR_M))
        self.depth_prog = shaders.program(ctx, "projector_depth.vert.glsl", "projector_depth.frag.glsl")
        self.line_prog = shaders.program(ctx, "projector_line.vert.glsl", "projector_line.frag.glsl",
                                         defines={"DEPTH_TOLERANCE": f"{float(depth_tolerance):.6f}",
                                                  "MIN_FACING": f"{float(np.cos(np.deg2rad(max_incidence_deg))):.6f}"})
        self.depth_prog["projection"].write(projection)
        self.line_prog["projection"].write(projection)
        self.line_prog["color"].value = tuple(float(c) / 255.0 for c in color)
        self.line_prog["bone_depth"].value = 0

        v = np.asarray(vertices, dtype=np.float32)
        f = np.asarray(faces, dtype=np.int32)
        self._bone_vbo = ctx.buffer(np.ascontiguousarray(v).tobytes())
        self._bone_ibo = ctx.buffer(np.ascontiguousarray(f).tobytes())
        self._bone_vao = ctx.vertex_array(self.depth_prog, [(self._bone_vbo, "3f", "in_position")], self._bone_ibo)
        ribbons, normals = ribbon_triangles(plan, np.asarray(vertices, dtype=float), np.asarray(faces), self.line_width)
        interleaved = np.concatenate([ribbons.reshape(-1, 3), normals.reshape(-1, 3)], axis=1)
        self._line_vbo = ctx.buffer(np.ascontiguousarray(interleaved, dtype=np.float32).tobytes())
        self._line_vao = ctx.vertex_array(self.line_prog, [(self._line_vbo, "3f 3f", "in_position", "in_normal")])

        self.depth_texture = ctx.texture(size, 1, dtype="f4")
        self.depth_texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._zbuffer = ctx.depth_renderbuffer(size)
        self._depth_fbo = ctx.framebuffer(color_attachments=[self.depth_texture], depth_attachment=self._zbuffer)
        self.color_texture = ctx.texture(size, 3)
        self._color_fbo = ctx.framebuffer(color_attachments=[self.color_texture])

    def render_depth(self, T_projector_bone: np.ndarray) -> np.ndarray:
        """(H, W) float32 linear depth of the bone seen from the projector, metres (0 = no bone)."""
        self._draw_depth(T_projector_bone)
        h, w = self.projector.height, self.projector.width
        return gl_rows_to_image(np.frombuffer(self.depth_texture.read(), dtype=np.float32).reshape(h, w))

    def render(self, T_projector_bone: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 projector image of the plan on the bone at ``T_projector_bone`` (4, 4)."""
        T = mat4_to_glsl(T_projector_bone)
        self._draw_depth(T_projector_bone)
        self._color_fbo.use()
        self._color_fbo.viewport = (0, 0, self.projector.width, self.projector.height)
        self._color_fbo.clear(0.0, 0.0, 0.0, 1.0)
        self.ctx.enable_only(moderngl.NOTHING)
        self.depth_texture.use(location=0)
        self.line_prog["T_projector_bone"].write(T)
        self._line_vao.render(moderngl.TRIANGLES)
        h, w = self.projector.height, self.projector.width
        rows = np.frombuffer(self.color_texture.read(alignment=1), dtype=np.uint8).reshape(h, w, 3)
        return np.ascontiguousarray(rows[::-1])

    def _draw_depth(self, T_projector_bone: np.ndarray) -> None:
        self._depth_fbo.use()
        self._depth_fbo.viewport = (0, 0, self.projector.width, self.projector.height)
        self._depth_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.depth_prog["T_projector_bone"].write(mat4_to_glsl(T_projector_bone))
        self._bone_vao.render(moderngl.TRIANGLES)

    def release(self) -> None:
        unbind_framebuffer(self.ctx)
        for obj in (self._depth_fbo, self._color_fbo, self._zbuffer, self.depth_texture, self.color_texture,
                    self._bone_vao, self._line_vao, self._bone_vbo, self._bone_ibo, self._line_vbo,
                    self.depth_prog, self.line_prog):
            obj.release()
