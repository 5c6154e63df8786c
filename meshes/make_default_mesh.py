"""Generate osteonav's default iliac-crest-like meshes, reproducibly (no randomness).

    python meshes/make_default_mesh.py [--out DIR]

writes ``meshes/iliac_crest.ply`` (about 5,000 triangles) and ``meshes/iliac_crest_tracking.ply``
(decimated to 1,000 for tracking). The shape: an S-curved ridge about 12 cm long whose cross-section
is a rounded, asymmetric arch 2-3.5 cm wide, thickened at one end like the iliac tubercle, with
flaring walls that run 4.5 cm down like the upper iliac wing; an open surface, like the cropped
crests in ../shared/data/pelvis. No symmetry, so every pose is observable. Metres, centred on the
bounding-box centre, z towards the crest's top.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

N_ALONG, N_ACROSS = 100, 26
LENGTH = 0.12
DEPTH = 0.045


def crest_surface() -> trimesh.Trimesh:
    s = np.linspace(-0.5, 0.5, N_ALONG)                      # along the crest
    theta = np.linspace(0.0, np.pi, N_ACROSS)                # across: 0 = lateral wall bottom, pi = medial
    S, TH = np.meshgrid(s, theta, indexing="ij")
    x = LENGTH * S
    y_centre = 0.012 * np.sin(2.6 * S) + 0.006 * np.sin(6.0 * S + 0.4)   # S-curve
    half_width = 0.011 + 0.004 * (S + 0.5) + 0.006 * np.exp(-((S - 0.32) / 0.09) ** 2)  # tubercle near one end
    ridge = 1.0 - 0.18 * (2 * S) ** 2 + 0.06 * S                           # the ridge's height profile
    # arch: the top is the rounded crest, the walls go down and flare outwards (wider below)
    down = np.clip(-np.sin(TH) + 1.0, 0.0, 1.0)              # 0 at the top, 1 at the wall bottoms
    flare = 1.0 + 0.9 * down**1.5 * np.where(TH < np.pi / 2, 1.3, 0.8)    # lateral flares more than medial
    y = y_centre + half_width * np.cos(TH) * flare
    z = DEPTH * (ridge * np.sin(TH) ** 0.6 - 1.0) * 0.82 + 0.004 * np.sin(5 * S) * np.sin(TH)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(N_ALONG * N_ACROSS).reshape(N_ALONG, N_ACROSS)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    if mesh.face_normals[:, 2].mean() < 0:    # normals outwards (up through the crest's top)
        mesh.invert()
    return mesh


def main() -> None:
    import argparse

    from app.mesh import outward_wound, prepare_mesh

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE, help="output folder (default: meshes/)")
    out = parser.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    mesh = crest_surface()
    mesh.export(out / "iliac_crest.ply")
    tracking = prepare_mesh(mesh, max_triangles=1000, center=False)
    tracking.export(out / "iliac_crest_tracking.ply")
    print(f"iliac_crest.ply: {len(mesh.faces)} triangles, extents {np.round(mesh.extents, 4)} m, outward {outward_wound(mesh)}")
    print(f"iliac_crest_tracking.ply: {len(tracking.faces)} triangles")


if __name__ == "__main__":
    main()
