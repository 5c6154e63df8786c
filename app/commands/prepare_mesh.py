"""``osteonav prepare-mesh INPUT --out OUT [--triangles 1000] [--scale S] [--no-center]``: a tracking mesh.

Loads any mesh trimesh reads, scales it (``--scale 0.001`` for a CT mesh in millimetres), checks
that it is plausibly in metres, centres it on its bounding-box centre (unless ``--no-center``) and
decimates it to the triangle budget (quadric decimation, :func:`app.mesh.prepare_mesh`). It prints
the triangle counts, the extents and the centring offset: a plan defined on the input mesh must be
moved the same way, p_out = scale * p_in - offset.
"""
from __future__ import annotations

from app.cli_types import finite_positive_float, int_at_least
from app.commands.outdir import add_overwrite_argument, prepare_file


EXPORT_FORMATS = ("ply", "stl", "obj", "off", "glb")
"""Mesh formats --out may name (all written by trimesh and read back by osteonav)."""


def register(subparsers) -> None:
    p = subparsers.add_parser("prepare-mesh", help="scale, centre and decimate a bone mesh for tracking")
    p.add_argument("input", help="mesh file (PLY, STL, OBJ, ...)")
    p.add_argument("--out", required=True, help="output mesh file (format from its suffix)")
    p.add_argument("--triangles", type=int_at_least(4), default=1000, help="triangle budget, >= 4 (default 1000)")
    p.add_argument("--scale", type=finite_positive_float, default=1.0,
                   help="scale factor from file units to metres, > 0: 0.001 for millimetres, 0.01 for centimetres "
                        "(default 1: the file is in metres)")
    p.add_argument("--no-center", action="store_true", help="keep the mesh's own origin (no centring)")
    add_overwrite_argument(p, "an existing --out file")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from app.errors import MeshError
    from app.mesh import check_triangles, check_units, load_mesh, outward_wound, prepare_mesh

    suffix = Path(args.out).suffix.lower().lstrip(".")
    if suffix not in EXPORT_FORMATS:
        raise MeshError(f"--out {args.out}: cannot write a mesh as {suffix or 'a file without a suffix'!r}; "
                        f"use one of: {', '.join('.' + f for f in EXPORT_FORMATS)}")
    mesh = load_mesh(args.input, check=False)
    n_in, extents_in = len(mesh.faces), mesh.extents.copy()
    if args.scale != 1.0:
        mesh.apply_scale(args.scale)
    check_units(mesh, args.input)
    check_triangles(mesh, args.input)   # a scale can underflow every triangle's area
    out = prepare_mesh(mesh, max_triangles=args.triangles, center=not args.no_center)
    check_triangles(out, args.out)
    prepare_file(args.out, args.overwrite, inputs=[args.input])
    out.export(args.out)
    offset = np.asarray(out.metadata["centering_offset"])
    fmt = lambda v: "[" + ", ".join(f"{x:.6f}" for x in v) + "]"  # noqa: E731
    print(f"input:  {args.input}: {n_in} triangles, extents {fmt(extents_in)} (file units)")
    if args.scale != 1.0:
        print(f"scale:  {args.scale:g} (file units -> metres)")
    print(f"output: {args.out}: {len(out.faces)} triangles, extents {fmt(out.extents)} m")
    print(f"centring offset: {fmt(offset)} m (p_out = {args.scale:g} * p_in - offset; move the plan the same way)")
    if len(out.faces) > args.triangles:
        print(f"warning: the simplifier stopped at {len(out.faces)} triangles, above --triangles {args.triangles}; "
              "the tracker decimates again to its render.mesh_triangles budget")
    if not outward_wound(out):
        print("warning: triangles are not consistently wound outwards; the tracker's back-face handling may suffer")
    return 0
