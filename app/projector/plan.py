"""Osteotomy plans: the outline to project, as polylines in the bone frame.

A :class:`Plan` is a list of 3D polylines in the bone (mesh) frame, metres, lying on the bone
surface. It comes from one of three sources, all checked against the bone mesh:

1. **A polyline file** (YAML, this format; units ``m`` or ``mm``)::

       # osteonav plan: cut polylines in the bone frame
       name: box_left           # optional
       units: mm                # m (default) | mm
       polylines:
         - closed: true         # the last point joins the first
           points: [[-10.0, -5.0, 19.0], [10.0, -5.0, 19.0], [10.0, 5.0, 19.0], [-10.0, 5.0, 19.0]]

2. **A transplant mesh** exported by planning software (STL, OBJ, PLY; metres): its outline is
   the set of its boundary edges and sharp edges (dihedral angle above ``feature_angle_deg``)
   that lie on the bone surface; edges inside the bone (the bottom of the cut) are dropped.

3. **Generated on the crest** for the demo: publication A's ``box`` (a 20 x 10 mm rectangle) and
   ``hockey`` (a hockey-stick outline: a shaft along the crest and a blade down one wall), drawn
   in the bone's x-y plane and dropped along -z onto the mesh (the crest's top is +z, see
   meshes/make_default_mesh.py).

Every point is moved to the nearest bone surface point after densifying to ``spacing`` (the
template is drawn where the cut meets the bone), and a point farther than ``tolerance`` (default
2 mm) from the surface raises :class:`app.errors.MeshError` (a plan made for another mesh, the
wrong units, the wrong frame). Unreadable or malformed files raise MeshError or ConfigError.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.errors import ConfigError, MeshError
from app.projector.geometry import closest_points_on_mesh, ray_mesh_first_hit

log = logging.getLogger(__name__)

PLAN_TOLERANCE_M = 0.002
"""Largest distance of a plan point from the bone surface (metres): planning and segmentation
error stay below ~1 mm; 2 mm catches a plan made for another mesh or in the wrong frame."""
PLAN_SPACING_M = 0.0005
"""Polylines are resampled at this spacing so the drawn line follows the curved bone surface."""
SHAPES = ("box", "hockey")
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")


@dataclass(frozen=True)
class Plan:
    """Outline polylines on the bone.

    polylines : tuple of (N_i, 3) float64 arrays, bone frame, metres, on the bone surface; a closed
        outline repeats its first point at the end.
    name : label for logs and file names.
    """

    polylines: tuple
    name: str = "plan"

    def segments(self) -> tuple[np.ndarray, np.ndarray]:
        """(a, b): (M, 3) start and end points of every segment of every polyline, bone frame."""
        a = np.concatenate([p[:-1] for p in self.polylines])
        b = np.concatenate([p[1:] for p in self.polylines])
        return a, b

    def points(self) -> np.ndarray:
        """(N, 3) all polyline points, bone frame."""
        return np.concatenate(self.polylines)

    def length(self) -> float:
        a, b = self.segments()
        return float(np.linalg.norm(b - a, axis=1).sum())


# --- building ------------------------------------------------------------------------------------

def densify(points: np.ndarray, spacing: float = PLAN_SPACING_M) -> np.ndarray:
    """A polyline with extra points so that no segment is longer than ``spacing`` (ends kept)."""
    pts = np.asarray(points, dtype=float)
    out = [pts[:1]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def snap_to_surface(plan: Plan, vertices: np.ndarray, faces: np.ndarray, tolerance: float = PLAN_TOLERANCE_M,
                    spacing: float = PLAN_SPACING_M, source: str = "plan") -> Plan:
    """The plan densified and moved onto the bone surface; MeshError if a point is farther than ``tolerance``."""
    polylines = []
    for i, line in enumerate(plan.polylines):
        dense = densify(line, spacing)
        closest, dist, _ = closest_points_on_mesh(dense, vertices, faces)
        worst = int(np.argmax(dist))
        if dist[worst] > tolerance:
            raise MeshError(
                f"{source}: polyline {i} is not on the bone: a point at {np.round(dense[worst] * 1000, 2).tolist()} mm "
                f"(bone frame) lies {dist[worst] * 1000:.1f} mm from the bone surface, more than the "
                f"{tolerance * 1000:.1f} mm tolerance. Is the plan in the bone mesh's frame and in metres "
                f"(units: mm in a YAML plan)?")
        polylines.append(closest)
    return Plan(tuple(polylines), plan.name)


def _drop_on_surface(xy: np.ndarray, vertices: np.ndarray, faces: np.ndarray, what: str) -> np.ndarray:
    """Points (x, y) in the bone frame dropped along -z onto the mesh (its first hit from above)."""
    top = float(np.max(vertices[:, 2])) + 0.05
    origins = np.column_stack([xy, np.full(len(xy), top)])
    t, _ = ray_mesh_first_hit(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)), vertices, faces)
    if not np.all(np.isfinite(t)):
        bad = xy[~np.isfinite(t)][0] * 1000
        raise MeshError(f"{what}: the outline leaves the bone at (x, y) = {np.round(bad, 1).tolist()} mm; "
                        f"make it smaller or move its centre")
    return origins + t[:, None] * np.array([0.0, 0.0, -1.0])


def _crest_line_y(x: float, vertices: np.ndarray, faces: np.ndarray) -> float:
    """y of the crest's highest point at position x along the bone (its ridge)."""
    lo, hi = vertices[:, 1].min(), vertices[:, 1].max()
    ys = np.linspace(lo, hi, 121)
    top = float(np.max(vertices[:, 2])) + 0.05
    t, _ = ray_mesh_first_hit(np.column_stack([np.full_like(ys, x), ys, np.full_like(ys, top)]),
                              np.tile([0.0, 0.0, -1.0], (len(ys), 1)), vertices, faces)
    if not np.any(np.isfinite(t)):
        raise MeshError(f"no bone surface at x = {x * 1000:.1f} mm (seen from +z)")
    return float(ys[np.argmin(t)])


def shape_outline(shape: str, length: float = 0.020, width: float = 0.010) -> np.ndarray:
    """Closed 2D outline (K, 2) in metres, centred at 0, u along the crest, v across it.

    ``box``: a length x width rectangle ((A): the graft is about 20 x 10 mm).
    ``hockey``: a shaft of length x width along the crest with a blade at its +u end, as wide as the
    shaft is long / 2.5, reaching 1.6 widths across to one side.
    """
    L, W = float(length), float(width)
    if shape == "box":
        pts = [(-L / 2, -W / 2), (L / 2, -W / 2), (L / 2, W / 2), (-L / 2, W / 2)]
    elif shape == "hockey":
        blade = L / 2.5
        pts = [(-L / 2, -W / 2), (L / 2, -W / 2), (L / 2, W / 2 + 1.6 * W), (L / 2 - blade, W / 2 + 1.6 * W),
               (L / 2 - blade, W / 2), (-L / 2, W / 2)]
    else:
        raise ConfigError("plan.shape", f"unknown shape {shape!r}; valid: {', '.join(SHAPES)}")
    pts = np.asarray(pts)
    return np.vstack([pts, pts[:1]])


def make_crest_plan(shape: str, vertices: np.ndarray, faces: np.ndarray, center_x: float = 0.0,
                    length: float = 0.020, width: float = 0.010, angle_deg: float = 0.0,
                    spacing: float = PLAN_SPACING_M, center_y: float | None = None) -> Plan:
    """Publication A's ``box`` or ``hockey`` outline drawn on the crest's top.

    Parameters
    ----------
    shape : 'box' | 'hockey'
    vertices, faces : the bone mesh (bone frame, metres, crest top towards +z)
    center_x : position of the outline's centre along the bone's x axis, metres
    center_y : its y, metres; None: the ridge's (the crest's highest point at ``center_x``)
    length, width : size of the box / the hockey stick's shaft, metres
    angle_deg : rotation of the outline about +z
    """
    vertices = np.asarray(vertices, dtype=float)
    y0 = _crest_line_y(center_x, vertices, faces) if center_y is None else float(center_y)
    a = np.deg2rad(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    outline2d = shape_outline(shape, length, width) @ R.T
    outline = densify(np.column_stack([outline2d, np.zeros(len(outline2d))]), spacing)[:, :2]
    xy = outline + np.array([center_x, y0])
    return Plan((_drop_on_surface(xy, vertices, faces, f"plan '{shape}'"),), shape)


RIDGE_GRID_M = 0.002
"""Cell of the top-view height map searched by :func:`derive_crest_plan` (metres)."""


def _height_map(vertices: np.ndarray, faces: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top view of the mesh: grid axes xs (X,), ys (Y,) and the first-hit height z (Y, X), NaN = no bone."""
    lo, hi = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
    xs, ys = np.arange(lo[0], hi[0] + cell, cell), np.arange(lo[1], hi[1] + cell, cell)
    gx, gy = np.meshgrid(xs, ys)
    top = float(np.max(vertices[:, 2])) + 0.05
    origins = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, top)])
    t, _ = ray_mesh_first_hit(origins, np.tile([0.0, 0.0, -1.0], (gx.size, 1)), vertices, faces)
    return xs, ys, np.where(np.isfinite(t), top - t, np.nan).reshape(gx.shape)


def derive_crest_plan(shape: str, vertices: np.ndarray, faces: np.ndarray, length: float = 0.020,
                      width: float = 0.010, angle_deg: float = 0.0, cell: float = RIDGE_GRID_M) -> Plan:
    """The outline of the configured size placed on this mesh's crest ridge, for a plan that does not fit it.

    The top view of the mesh is sampled on a ``cell`` grid (height z(x, y) of the first hit from +z).
    Every grid cell is tried as the centre and every 15 degrees (plus ``angle_deg``) as the direction;
    an outline fits when all its points (at ``cell`` spacing) land on the bone. Among those that fit,
    the one whose points lie highest on average, argmax_{c, a} mean_k z(c + R(a) p_k), is taken: it
    lies along the crest's ridge. MeshError when the outline fits nowhere on the mesh.
    """
    vertices = np.asarray(vertices, dtype=float)
    xs, ys, z = _height_map(vertices, faces, cell)
    outline = densify(np.column_stack([shape_outline(shape, length, width), np.zeros(5 if shape == "box" else 7)]),
                      cell)[:, :2]
    cy, cx = np.nonzero(np.isfinite(z))
    centres = np.column_stack([xs[cx], ys[cy]])
    best = (-np.inf, None, None)
    for angle in angle_deg + np.arange(0.0, 180.0, 15.0):
        a = np.deg2rad(angle)
        pts = outline @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).T
        ix = np.rint((centres[:, None, 0] + pts[None, :, 0] - xs[0]) / cell).astype(int)
        iy = np.rint((centres[:, None, 1] + pts[None, :, 1] - ys[0]) / cell).astype(int)
        inside = (ix >= 0) & (ix < len(xs)) & (iy >= 0) & (iy < len(ys))
        h = np.where(inside, z[np.clip(iy, 0, len(ys) - 1), np.clip(ix, 0, len(xs) - 1)], np.nan)
        fits = np.all(np.isfinite(h), axis=1)
        if fits.any():
            score = np.where(fits, np.nanmean(np.where(np.isfinite(h), h, 0.0), axis=1), -np.inf)
            k = int(np.argmax(score))
            if score[k] > best[0]:
                best = (score[k], centres[k], angle)
    if best[1] is None:
        raise MeshError(f"plan '{shape}': a {length * 1000:.0f} x {width * 1000:.0f} mm outline fits nowhere on the "
                        f"crest seen from +z")
    (x0, y0), angle = best[1], float(best[2])
    for dx, dy in ((0, 0), (cell / 2, 0), (-cell / 2, 0), (0, cell / 2), (0, -cell / 2)):
        try:   # the grid test is at cell resolution: nudge the centre if an edge ray just misses
            plan = make_crest_plan(shape, vertices, faces, x0 + dx, length, width, angle, center_y=y0 + dy)
        except MeshError:
            continue
        name = (f"{shape} derived from the mesh: centre ({(x0 + dx) * 1000:.1f}, {(y0 + dy) * 1000:.1f}) mm, "
                f"{angle % 180:.0f} deg on the ridge")
        return Plan(plan.polylines, name)
    raise MeshError(f"plan '{shape}': no outline along the ridge at ({x0 * 1000:.1f}, {y0 * 1000:.1f}) mm fits")


# --- files ---------------------------------------------------------------------------------------

def read_polyline_yaml(path: Path) -> Plan:
    """A plan from the YAML polyline format of the module docstring (not yet checked against a mesh)."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError("plan", f"cannot read {path}: {exc}") from None
    src = str(path)
    if not isinstance(data, dict) or "polylines" not in data:
        raise ConfigError("polylines", "missing; a plan file holds 'polylines: [{closed, points}, ...]'", src)
    units = data.get("units", "m")
    if units not in ("m", "mm"):
        raise ConfigError("units", f"expected 'm' or 'mm', got {units!r}", src)
    scale = 0.001 if units == "mm" else 1.0
    lines = data["polylines"]
    if not isinstance(lines, list) or not lines:
        raise ConfigError("polylines", "expected a non-empty list of {closed, points}", src)
    polylines = []
    for i, item in enumerate(lines):
        key = f"polylines[{i}]"
        if not isinstance(item, dict) or "points" not in item:
            raise ConfigError(key, "expected a mapping with 'points' (list of [x, y, z]) and optional 'closed'", src)
        try:
            pts = np.asarray(item["points"], dtype=float) * scale
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{key}.points", f"not a list of numbers: {exc}", src) from None
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.all(np.isfinite(pts)):
            raise ConfigError(f"{key}.points", f"expected at least 2 finite [x, y, z] points, got shape {pts.shape}", src)
        if item.get("closed", False):
            pts = np.vstack([pts, pts[:1]])
        polylines.append(pts)
    return Plan(tuple(polylines), str(data.get("name", Path(path).stem)))


def write_polyline_yaml(path: Path, plan: Plan, units: str = "mm") -> None:
    """Write a plan in the YAML polyline format (closed outlines written with ``closed: true``)."""
    import yaml

    scale = 1000.0 if units == "mm" else 1.0
    items = []
    for line in plan.polylines:
        closed = len(line) > 2 and np.allclose(line[0], line[-1])
        pts = line[:-1] if closed else line
        items.append({"closed": bool(closed), "points": np.round(pts * scale, 4).tolist()})
    text = "# osteonav plan: cut polylines in the bone frame (app/projector/plan.py)\n"
    text += yaml.safe_dump({"name": plan.name, "units": units, "polylines": items}, default_flow_style=None, sort_keys=False)
    Path(path).write_text(text)


def mesh_outline(path: Path, vertices: np.ndarray, faces: np.ndarray, tolerance: float = PLAN_TOLERANCE_M,
                 feature_angle_deg: float = 30.0) -> Plan:
    """Outline of a transplant mesh on the bone: its boundary and sharp edges that lie on the bone surface."""
    from app.mesh import load_mesh

    mesh = load_mesh(path)
    edges_sorted = np.sort(mesh.edges_sorted, axis=1)
    uniq, counts = np.unique(edges_sorted, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    sharp = mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.deg2rad(feature_angle_deg)]
    edges = np.unique(np.sort(np.vstack([boundary, sharp]), axis=1), axis=0) if len(boundary) + len(sharp) else boundary
    if len(edges) == 0:
        raise MeshError(f"{path}: the transplant mesh has no boundary or sharp edges to outline")
    v = np.asarray(mesh.vertices, dtype=float)
    _, dist, _ = closest_points_on_mesh(v, vertices, faces)
    on = dist <= tolerance
    keep = edges[on[edges[:, 0]] & on[edges[:, 1]]]
    if len(keep) == 0:
        raise MeshError(f"{path}: no edge of the transplant mesh lies on the bone (its vertices are "
                        f"{dist.min() * 1000:.1f} mm or more from the bone surface, tolerance "
                        f"{tolerance * 1000:.1f} mm); is it in the bone mesh's frame and in metres?")
    log.info("%s: %d of %d outline edges lie on the bone", path, len(keep), len(edges))
    return Plan(tuple(v[e] for e in keep), Path(path).stem)


def load_plan(path: "str | Path", vertices: np.ndarray, faces: np.ndarray, tolerance: float = PLAN_TOLERANCE_M,
              spacing: float = PLAN_SPACING_M) -> Plan:
    """A plan file (YAML polylines or a transplant mesh), checked against and snapped onto the bone mesh."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("plan", f"plan file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        raw = read_polyline_yaml(path)
    elif suffix in MESH_SUFFIXES:
        raw = mesh_outline(path, vertices, faces, tolerance)
    else:
        raise ConfigError("plan", f"{path}: unknown plan format {suffix!r}; use a YAML polyline file or a mesh "
                          f"({', '.join(MESH_SUFFIXES)})")
    return snap_to_surface(raw, vertices, faces, tolerance, spacing, source=str(path))
