"""The one place osteonav creates OpenGL contexts.

A standalone EGL context (no window, no display server) of at least OpenGL 4.3 (compute shaders).
On a machine with a GPU driver EGL picks the GPU; without one, Mesa's llvmpipe runs the same code
in software. :func:`describe` reports which of the two a context got, so benchmarks and logs can
say where they ran.

GL hygiene (STYLE.md §10): only the thread that created a context may use it. Renderers release
their GL objects explicitly in ``release()``.
"""
from __future__ import annotations

import logging
import os
import threading

import moderngl

from app.errors import GLError

log = logging.getLogger(__name__)

REQUIRED_GL = 430  # compute shaders and shader storage buffers
_local = threading.local()


def create_context() -> moderngl.Context:
    """Create a new standalone EGL context (GL >= 4.3); raise :class:`GLError` naming what was found.

    The new context becomes this thread's current one: moderngl does not switch contexts by itself, so
    every GL call made afterwards through another context object (say the :func:`shared_context`)
    runs on this one instead, and that context's objects do not exist here (GL_INVALID_OPERATION).
    Code that renders should take :func:`shared_context`, which makes its context current again.
    """
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=REQUIRED_GL)
    except Exception as exc:  # moderngl raises plain Exception subclasses for EGL failures
        hint = (
            "osteonav needs OpenGL >= 4.3 through EGL. Without a GPU, install Mesa: "
            "sudo apt-get install -y libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgbm1"
        )
        raise GLError(f"cannot create an EGL OpenGL {REQUIRED_GL // 100}.{REQUIRED_GL % 100 // 10} context: {exc}. {hint}") from exc
    if ctx.version_code < REQUIRED_GL:
        found = ctx.version_code
        ctx.release()
        raise GLError(f"OpenGL {found} found, {REQUIRED_GL} (compute shaders) required")
    log.info("OpenGL context: %s", describe(ctx))
    return ctx


def shared_context() -> moderngl.Context:
    """This thread's context, created on first use and reused afterwards; current in this thread on return.

    A context created in this thread since (:func:`create_context`, :func:`describe_default_context`)
    took the thread's current binding; without making this one current again, renderers built on it
    would issue their calls to that other context, with object names it does not have.
    """
    ctx = getattr(_local, "ctx", None)
    if ctx is None:
        ctx = create_context()
        _local.ctx = ctx
    else:
        make_current(ctx)
    return ctx


def make_current(ctx: moderngl.Context) -> None:
    """Make ``ctx`` this thread's current context (eglMakeCurrent; under a microsecond when it already is).

    moderngl's ``with ctx:`` does this and restores the previous context on exit; here the switch is
    meant to last, so the exit is not called.
    """
    ctx.__enter__()


def is_software(ctx: moderngl.Context) -> bool:
    """True when the context runs on a CPU rasteriser (llvmpipe, softpipe, swrast, lavapipe)."""
    renderer = ctx.info.get("GL_RENDERER", "").lower()
    return any(name in renderer for name in ("llvmpipe", "softpipe", "swrast", "software"))


def describe(ctx: moderngl.Context) -> str:
    """One line: renderer, GL version and whether it is a GPU or software rendering."""
    kind = "software (no GPU)" if is_software(ctx) else "GPU"
    threads = os.environ.get("LP_NUM_THREADS")
    extra = f", LP_NUM_THREADS={threads}" if threads else ""
    return f"{ctx.info.get('GL_RENDERER', '?')} / OpenGL {ctx.info.get('GL_VERSION', '?')} [{kind}{extra}]"


def describe_default_context() -> str:
    """Create a throwaway context and describe it (used by the setup script as a smoke test)."""
    ctx = create_context()
    try:
        return describe(ctx)
    finally:
        ctx.release()
        shared = getattr(_local, "ctx", None)
        if shared is not None:   # the throwaway took the thread's current binding: give it back
            make_current(shared)


def unbind_framebuffer(ctx: moderngl.Context) -> None:
    """Bind a 1x1 framebuffer kept for this purpose.

    A standalone EGL context has no default framebuffer; moderngl rebinds the last bound one after
    creating another, so releasing a bound framebuffer would leave GL_INVALID_OPERATION behind.
    Renderers call this before releasing their own framebuffer.
    """
    extra = ctx.extra if isinstance(ctx.extra, dict) else {}
    idle = extra.get("idle_framebuffer")
    if idle is None:
        idle = ctx.framebuffer(color_attachments=[ctx.renderbuffer((1, 1))])
        extra["idle_framebuffer"] = idle
        ctx.extra = extra
    idle.use()
