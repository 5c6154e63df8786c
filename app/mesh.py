"""Bone meshes: loading, the unit check, and preparation for tracking (centring, decimation).

CT-derived meshes come in millimetres more often than not (sometimes centimetres); osteonav works
in metres, so a mesh whose largest extent exceeds ``MAX_EXTENT_M`` is rejected with the fix (the
``--scale`` that makes it bone-sized: 0.001 for millimetres, 0.01 for centimetres), never silently
rescaled. A mesh without a triangle of non-zero area is refused at load. Decimation uses fast-simplification (quadric error metrics) down to a triangle
budget: the tracker renders the mesh N times per frame, so its cost is linear in the triangles.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from app.errors import MeshError

log = logging.getLogger(__name__)

MAX_EXTENT_M = 1.0   # no bone is a metre long: larger means millimetres or centimetres
MIN_EXTENT_M = 0.005
BONE_EXTENT_M = (0.02, 0.6)   # a plausible tracked bone (a cropped crest to a whole pelvis): picks the unit's scale
UNIT_SCALES = {"millimetres": 0.001, "centimetres": 0.01}


def load_mesh(path: str | Path, check: bool = True) -> trimesh.Trimesh:
    """One triangle mesh from any file trimesh reads (a scene's geometries are merged).

    ``check`` (default): also :func:`check_units`, so every mesh osteonav loads is in metres;
    only prepare-mesh, which scales first, loads without it.
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: cannot read the mesh ({exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{path}: no triangles found")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{path}: vertices contain NaN or infinite values")
    check_triangles(loaded, path)
    if check:
        check_units(loaded, path)
    return loaded


def check_triangles(mesh: trimesh.Trimesh, source: str | Path = "mesh") -> None:
    """Raise :class:`MeshError` when no triangle has an area (every one has repeated or collinear
    vertices): nothing to render or fit, the tracker's kernels would fail on it."""
    extent = float(np.max(mesh.extents)) if len(mesh.vertices) else 0.0
    areas = np.asarray(mesh.area_faces)
    if not np.any(areas > 1e-12 * max(extent, 1e-300) ** 2):
        raise MeshError(f"{source}: all {len(mesh.faces)} triangles are degenerate (zero area: repeated or collinear "
                        "vertices); export the bone's surface again")


def unit_guesses(extent: float) -> list[tuple[str, float]]:
    """(unit, scale) of the units in which a mesh ``extent`` file units across is bone-sized (``BONE_EXTENT_M``)."""
    low, high = BONE_EXTENT_M
    return [(unit, s) for unit, s in UNIT_SCALES.items() if low <= extent * s <= high]


def check_units(mesh: trimesh.Trimesh, source: str | Path = "mesh") -> None:
    """Raise :class:`MeshError` unless the mesh's size is plausible for a bone in metres.

    The message gives the fix: the prepare-mesh command line that converts the file, with the scale of
    the unit that makes it bone-sized (both when millimetres and centimetres would).
    """
    extent = float(np.max(mesh.extents))
    out = Path(str(source)).with_name(Path(str(source)).stem + "_m.ply")
    if extent > MAX_EXTENT_M:
        guesses = unit_guesses(extent) or list(UNIT_SCALES.items())
        sizes = " or ".join(f"{unit} ({100 * extent * s:.3g} cm across with --scale {s:g})" for unit, s in guesses)
        raise MeshError(f"mesh {source} is ~{extent:.3g} m across if in metres: it looks like {sizes}; osteonav "
                        f"needs metres; run: osteonav prepare-mesh {source} --out {out} --scale {guesses[0][1]:g}")
    if extent < MIN_EXTENT_M:
        raise MeshError(f"mesh {source} is ~{extent:.3g} m across, too small for a bone; check its units "
                        f"(osteonav prepare-mesh {source} --out {out} --scale S converts them)")


def decimate(mesh: trimesh.Trimesh, max_triangles: int, passes: int = 4) -> trimesh.Trimesh:
    """The mesh reduced to at most ``max_triangles`` (quadric decimation), or unchanged if smaller.

    The simplifier can stop above its target; it is run again (up to ``passes`` in all) while it still
    makes progress. The result may stay above the budget: the caller says so (prepare-mesh)."""
    if len(mesh.faces) <= max_triangles:
        return mesh.copy()
    import fast_simplification

    reduction = 1.0 - max_triangles / len(mesh.faces)
    vertices, faces = fast_simplification.simplify(np.asarray(mesh.vertices, dtype=np.float32),
                                                   np.asarray(mesh.faces, dtype=np.int32), target_reduction=reduction)
    out = trimesh.Trimesh(np.asarray(vertices, dtype=float), faces, process=True)
    for _ in range(passes - 1):
        if len(out.faces) <= max_triangles:
            break
        vertices, faces = fast_simplification.simplify(np.asarray(out.vertices, dtype=np.float32),
                                                       np.asarray(out.faces, dtype=np.int32), target_count=max_triangles)
        before, out = len(out.faces), trimesh.Trimesh(np.asarray(vertices, dtype=float), faces, process=True)
        if len(out.faces) >= before:
            break
    return out


def prepare_mesh(mesh: trimesh.Trimesh, max_triangles: int = 1000, center: bool = True) -> trimesh.Trimesh:
    """A tracking mesh: optionally centred on its bounding-box centre, decimated to the budget.

    The centring offset (metres, subtracted from every vertex) is in ``mesh.metadata['centering_offset']``;
    a plan defined on the original mesh must be moved by the same offset.
    """
    out = mesh.copy()
    offset = np.zeros(3)
    if center:
        offset = out.bounds.mean(axis=0)
        out.apply_translation(-offset)
    out = decimate(out, max_triangles)
    out.metadata["centering_offset"] = offset.tolist()
    log.info("prepared mesh: %d -> %d triangles, centring offset %s m", len(mesh.faces), len(out.faces),
             np.round(offset, 6).tolist())
    return out


def outward_wound(mesh: trimesh.Trimesh) -> bool:
    """True when triangles wind consistently and counter-clockwise seen from outside.

    For an open surface (a cropped crest) "outside" is judged by the signed volume of the cone from
    the centroid, positive when the normals point away from it.
    """
    if not mesh.is_winding_consistent:
        return False
    tri = mesh.triangles - mesh.centroid
    signed = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    return bool(signed > 0)
