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
    """Create a new standalone EGL context (GL >= 4.3); raise :class:`GLError` naming what was found."""
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
    """This thread's context, created on first use and reused afterwards."""
    ctx = getattr(_local, "ctx", None)
    if ctx is None:
        ctx = create_context()
        _local.ctx = ctx
    return ctx


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
