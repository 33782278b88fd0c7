"""One offscreen OpenGL context per process (moderngl on EGL; llvmpipe works)."""

from __future__ import annotations

import logging
import os

import moderngl

log = logging.getLogger(__name__)

_CONTEXT: moderngl.Context | None = None
_CONTEXT_PID: int | None = None

_HELP = (
    "could not create a headless OpenGL context with EGL ({err}). moderngl needs the EGL "
    "loader and a Mesa driver: install the system packages libegl1 and libgl1-mesa-dri "
    "(Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri); on a machine without a GPU "
    "Mesa's llvmpipe is used."
)


def create_context(require: tuple[int, int] = (3, 3)) -> moderngl.Context:
    """The process's standalone moderngl context on the EGL backend, created on first use.

    A forked child gets its own context (a context does not survive fork).

    Raises
    ------
    RuntimeError naming the missing system packages if EGL cannot be initialised.
    """
    global _CONTEXT, _CONTEXT_PID
    pid = os.getpid()
    if _CONTEXT is not None and _CONTEXT_PID == pid:
        return _CONTEXT
    try:
        ctx = moderngl.create_standalone_context(
            backend="egl", require=require[0] * 100 + require[1] * 10
        )
    except Exception as err:  # moderngl/glcontext raise plain Exceptions
        raise RuntimeError(_HELP.format(err=err)) from err
    info = ctx.info
    log.info(
        "OpenGL context: %s / %s / %s",
        info.get("GL_VENDOR"),
        info.get("GL_RENDERER"),
        info.get("GL_VERSION"),
    )
    _CONTEXT, _CONTEXT_PID = ctx, pid
    return ctx
