"""Loading GLSL sources from the ``.glsl`` files beside this module.

``load_source(name, defines)`` reads ``app/render/<name>``, inserts ``#define KEY VALUE`` lines right
after the ``#version`` line (work-group sizes, tile sizes, options), and ``program()`` /
``compute_shader()`` compile them; a compile or link failure raises :class:`GLError` with the file
paths, the stage and the source with line numbers, so the driver's line references can be read.
"""
from __future__ import annotations

from pathlib import Path

import moderngl

from app.errors import GLError

SHADER_DIR = Path(__file__).resolve().parent


def load_source(name: str, defines: dict[str, object] | None = None) -> str:
    """GLSL source of ``SHADER_DIR / name`` with ``defines`` injected after ``#version``."""
    path = SHADER_DIR / name
    source = path.read_text()
    lines = source.splitlines()
    if not lines or not lines[0].startswith("#version"):
        raise GLError(f"{path}: the first line must be a #version directive")
    injected = [f"#define {key} {value}" for key, value in (defines or {}).items()]
    return "\n".join([lines[0], *injected, *lines[1:]]) + "\n"


def _numbered(source: str) -> str:
    return "\n".join(f"{i + 1:4d}: {line}" for i, line in enumerate(source.splitlines()))


def program(
    ctx: moderngl.Context,
    vertex: str,
    fragment: str,
    defines: dict[str, object] | None = None,
) -> moderngl.Program:
    """Compile and link a vertex + fragment program from two .glsl files."""
    vs = load_source(vertex, defines)
    fs = load_source(fragment, defines)
    try:
        return ctx.program(vertex_shader=vs, fragment_shader=fs)
    except moderngl.Error as exc:
        raise GLError(
            f"compiling {SHADER_DIR / vertex} + {SHADER_DIR / fragment} failed:\n{exc}\n"
            f"--- {vertex}\n{_numbered(vs)}\n--- {fragment}\n{_numbered(fs)}"
        ) from exc


def compute_shader(
    ctx: moderngl.Context, name: str, defines: dict[str, object] | None = None
) -> moderngl.ComputeShader:
    """Compile a compute shader from a .glsl file."""
    src = load_source(name, defines)
    try:
        return ctx.compute_shader(src)
    except moderngl.Error as exc:
        raise GLError(f"compiling compute shader {SHADER_DIR / name} failed:\n{exc}\n{_numbered(src)}") from exc
