"""Which likelihood backend the tracker uses: ``render.backend`` = auto | gl | cpu.

``auto`` picks ``cpu`` when the GL context is a software renderer (Mesa's llvmpipe, softpipe,
swrast: :func:`app.render.context.is_software`) or when no GL context can be created at all, and
``gl`` on a GPU (issue 13: on a 2-core machine the numba backend is about 10x llvmpipe;
BENCHMARKS.md §1). ``cpu`` never creates a GL context.

Usage::

    backend, description = make_backend("auto", vertices, faces, camera_160x120, capacity=200,
                                        params=params, near=0.05, far=4.0, cull_back_faces=True)
"""
from __future__ import annotations

import logging

import numpy as np

from app.errors import GLError
from app.filter.likelihood_ref import LikelihoodParams
from app.filter.observation import BACKENDS
from app.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)


def resolve(choice: str) -> tuple[str, str]:
    """('gl' | 'cpu', why) for a ``render.backend`` value; 'auto' looks at the GL context."""
    if choice not in BACKENDS:
        raise ValueError(f"render.backend {choice!r} is not one of: {', '.join(BACKENDS)}")
    if choice != "auto":
        return choice, "configured"
    from app.render.context import describe, is_software, shared_context

    try:
        ctx = shared_context()
    except GLError as exc:
        log.warning("no OpenGL context (%s): the cpu likelihood backend runs", exc)
        return "cpu", "auto: no OpenGL context"
    if is_software(ctx):
        return "cpu", f"auto: GL is {describe(ctx)}"
    return "gl", "auto: GL runs on a GPU"


def make_backend(choice: str, vertices: np.ndarray, faces: np.ndarray, camera: PinholeCamera, capacity: int,
                 params: LikelihoodParams, near: float, far: float, cull_back_faces: bool):
    """(backend, one-line description saying which backend runs and why) for ``render.backend``."""
    name, why = resolve(choice)
    if name == "cpu":
        from app.render.cpu_likelihood import CPULikelihoodBackend

        backend = CPULikelihoodBackend(vertices, faces, camera, capacity, params, near=near, far=far,
                                       cull_back_faces=cull_back_faces)
    else:
        from app.render.context import shared_context
        from app.render.likelihood import GLLikelihoodBackend

        backend = GLLikelihoodBackend(shared_context(), vertices, faces, camera, capacity, params, near=near,
                                      far=far, cull_back_faces=cull_back_faces)
    description = f"{backend.describe()} [{why}]"
    log.info("likelihood backend: %s", description)
    return backend, description
