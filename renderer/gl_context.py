"""One offscreen OpenGL context per process (moderngl on EGL; llvmpipe works)."""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from typing import Any

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


# GL entry points and enums moderngl does not wrap (reversed-Z depth).
_GL_LOWER_LEFT = 0x8CA1
_GL_NEGATIVE_ONE_TO_ONE = 0x935E
_GL_ZERO_TO_ONE = 0x935F
_GL_RENDERBUFFER = 0x8D41
_GL_RENDERBUFFER_BINDING = 0x8CA7
_GL_DEPTH_COMPONENT32F = 0x8CAC


class ReversedZ:
    """What a reversed-Z depth buffer needs beyond moderngl: ``glClipControl`` (GL 4.5 or
    ARB_clip_control) and 32-bit float depth renderbuffers, through EGL's proc addresses.

    With clip z in [0, 1] (``zero_to_one``) and a projection whose clip z is ``near``
    (window depth ``near / z``, 1 at the near plane, 0 at infinity), a float depth buffer
    keeps a relative precision of ~1e-7 of the distance at every range, and the depth is
    exact when interpolated across a triangle (1/z is affine in screen space): no shader
    has to write ``gl_FragDepth``, so the rasterizer tests depth before shading.
    """

    def __init__(self, ctx: moderngl.Context) -> None:
        if not (ctx.version_code >= 450 or "GL_ARB_clip_control" in ctx.extensions):
            raise RuntimeError(
                f"the OpenGL context ({ctx.info.get('GL_RENDERER')}, "
                f"{ctx.info.get('GL_VERSION')}) lacks glClipControl (GL 4.5 or "
                "ARB_clip_control), which the object renderer's depth needs; Mesa's "
                "llvmpipe and current GPU drivers have it"
            )
        egl = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
        get = egl.eglGetProcAddress
        get.restype = ctypes.c_void_p
        get.argtypes = [ctypes.c_char_p]

        def entry(name: str, *args: type) -> Any:
            addr = get(name.encode())
            if not addr:
                raise RuntimeError(f"EGL has no {name}")
            return ctypes.CFUNCTYPE(None, *args)(addr)

        u, i = ctypes.c_uint, ctypes.c_int
        self._clip_control = entry("glClipControl", u, u)
        self._bind_rb = entry("glBindRenderbuffer", u, u)
        self._rb_storage = entry("glRenderbufferStorage", u, u, i, i)
        self._get_integer = entry("glGetIntegerv", u, ctypes.POINTER(ctypes.c_int))
        self.ctx = ctx

    def zero_to_one(self, on: bool) -> None:
        """Clip z in [0, w] (on) or OpenGL's default [-w, w] (off)."""
        self._clip_control(_GL_LOWER_LEFT, _GL_ZERO_TO_ONE if on else _GL_NEGATIVE_ONE_TO_ONE)

    def depth32f_renderbuffer(self, size: tuple[int, int]) -> moderngl.Renderbuffer:
        """A moderngl depth renderbuffer of ``size`` whose storage is GL_DEPTH_COMPONENT32F
        (moderngl's own is 24-bit fixed point)."""
        rb = self.ctx.depth_renderbuffer(size)
        bound = ctypes.c_int(0)
        self._get_integer(_GL_RENDERBUFFER_BINDING, ctypes.byref(bound))
        self._bind_rb(_GL_RENDERBUFFER, rb.glo)
        self._rb_storage(_GL_RENDERBUFFER, _GL_DEPTH_COMPONENT32F, int(size[0]), int(size[1]))
        self._bind_rb(_GL_RENDERBUFFER, bound.value)
        return rb


_REVERSED_Z: ReversedZ | None = None
_REVERSED_Z_PID: int | None = None


def reversed_z(ctx: moderngl.Context) -> ReversedZ:
    """The process's :class:`ReversedZ` for its context (:func:`create_context`)."""
    global _REVERSED_Z, _REVERSED_Z_PID
    if _REVERSED_Z is None or _REVERSED_Z_PID != os.getpid() or _REVERSED_Z.ctx is not ctx:
        _REVERSED_Z, _REVERSED_Z_PID = ReversedZ(ctx), os.getpid()
    return _REVERSED_Z
